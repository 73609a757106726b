"""The backbones' reaches into lerobot's internals, declared and checked, so that a lerobot upgrade's work list is
mechanical. Each backbone folder declares the private functions, methods and attributes of lerobot it reaches
(`graftcache.backbones.spec.BackboneSpec.lerobot_reaches`), each shared module of graftcache/backbones/ its own
(`LEROBOT_REACHES` beside its code). Read statically with the reader the rollout seam's boundary uses
(tests/helpers/reaches.py): every private reach in a home's code is one it declares, by attribute name (which class
the receiver is, the declaration says, read by hand in lerobot's source), and every declaration is used; torch's and
transformers' internals are listed apart (`OTHERS`), with why. Then every declared name must exist in the installed
lerobot (its module imported, its attributes followed; an attribute a class sets on its instances is found in the
class's source): after an upgrade this lists every name that moved, by backbone, at once."""

from __future__ import annotations

import ast
import inspect
import textwrap
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from importlib import import_module
from pathlib import Path

from helpers.reaches import PACKAGE, own_names, package_trees, private, reaches

from graftcache.backbone_registry import BACKBONES
from graftcache.backbones import registered_spec

FOLDER = PACKAGE / "backbones"
#: torch's and transformers' internals the backbones reach, by file (under graftcache/backbones/) and name, with why:
#: not lerobot's, so no backbone declares them and graftcache.upstream.WRITTEN_AGAINST does not pin them
OTHERS = {
    ("lean_load.py", "_parameters"): "torch.nn.Module's parameter slots: a read tensor set under each tied name",
    ("lean_load.py", "_buffers"): "torch.nn.Module's buffer slots: a read buffer set, buffers moved to the device",
    ("surgery.py", "_version"): "torch.Tensor's write counter: undoing a graft refuses a frozen tensor written",
    ("paligemma.py", "_vocab_size"): "transformers' PaliGemmaConfig vocabulary, set with the text config's for a tiny "
                                     "pi0 or pi0.5",
    ("wall_x/tiny.py", "_attn_implementation"): "transformers' config attention path, set as Wall-X's from_pretrained "
                                                "sets it",
    ("vla_jepa/tiny.py", "_from_config"): "transformers' PreTrainedModel._from_config: a Qwen3-VL built from its "
                                          "config, no weights read",
}


@dataclass
class Home:
    """Where reaches are declared: a backbone folder (its spec's `lerobot_reaches`) or a shared module of
    graftcache/backbones/ (its `LEROBOT_REACHES`)."""

    label: str
    #: file (relative to graftcache/backbones/) -> its code
    sources: dict[str, str]
    declared: tuple[str, ...]
    #: private names it reaches as data, by name: its spec's image method, which the adapter reads and patches
    by_name: tuple[str, ...] = ()


def _shared_declaration(source: str) -> tuple[str, ...]:
    """A shared module's module-level `LEROBOT_REACHES` (a literal tuple), read without importing the module."""
    for node in ast.parse(source).body:
        if isinstance(node, ast.Assign) and [ast.unparse(t) for t in node.targets] == ["LEROBOT_REACHES"]:
            return tuple(ast.literal_eval(node.value))
    return ()


def homes() -> list[Home]:
    """Every backbone folder's home, then every shared module's."""
    def code(paths: Iterable[Path]) -> dict[str, str]:
        return {path.relative_to(FOLDER).as_posix(): path.read_text() for path in sorted(paths)}

    folders = [Home(name, code((FOLDER / name).rglob("*.py")), spec.lerobot_reaches,
                    tuple(m for m in (spec.image_method,) if private(m)))
               for name in BACKBONES for spec in (registered_spec(name),)]
    shared = [Home(path.name, code([path]), _shared_declaration(path.read_text())) for path in FOLDER.glob("*.py")]
    return folders + sorted(shared, key=lambda home: home.label)


def found(home: Home, own: set[str], lerobot: set[str]) -> list[tuple[str, int, str, str]]:
    """(file, line, name, how) for each private name `home`'s code reaches past another library's API (`own`:
    graftcache's private names; `lerobot`: the names declared as lerobot's, found whoever else defines them)."""
    out = [(file, line, name, how) for file, source in home.sources.items()
           for line, name, how in reaches(ast.parse(source), own, set(), lerobot) if private(name)]
    return out + [(f"{home.label}/spec.py", 0, name, "SPEC.image_method") for name in home.by_name]


def _last(name: str) -> str:
    return name.rsplit(".", 1)[-1]


def undeclared(home: Home, own: set[str], lerobot: set[str]) -> list[str]:
    """A line per reach of `home`'s code that it does not declare (torch's and transformers', `OTHERS`, aside)."""
    names = {_last(name) for name in home.declared}
    return [f"{file}:{line}: {how} ({home.label} declares no {name})" for file, line, name, how in
            found(home, own, lerobot) if name not in names and (file, name) not in OTHERS]


def stale(home: Home, own: set[str], lerobot: set[str]) -> list[str]:
    """A line per name `home` declares that its code no longer reaches."""
    used = {name for _, _, name, _ in found(home, own, lerobot)}
    return [f"{home.label}: {name} declared, never reached" for name in home.declared if _last(name) not in used]


def _set_on_instances(cls: type) -> set[str]:
    """The attributes the methods of lerobot class `cls` and of its lerobot bases set on self: its instances'
    attributes, which the class itself lacks."""
    names = set()
    for klass in (k for k in cls.__mro__ if k.__module__.startswith("lerobot.")):
        tree = ast.parse(textwrap.dedent(inspect.getsource(klass)))
        names |= {n.attr for n in ast.walk(tree) if isinstance(n, ast.Attribute) and isinstance(n.ctx, ast.Store)
                  and isinstance(n.value, ast.Name) and n.value.id == "self"}
    return names


def missing(name: str) -> str | None:
    """Why fully qualified `name` is not in the installed lerobot, or None where it is: its longest importable
    module, then each attribute along the rest (the last may be one the class sets on its instances)."""
    parts = name.split(".")
    if parts[0] != "lerobot":
        return "not lerobot's"
    for cut in range(len(parts), 0, -1):
        module = ".".join(parts[:cut])
        try:
            found_object = import_module(module)
            break
        except ModuleNotFoundError as error:
            if not error.name or not (module == error.name or module.startswith(f"{error.name}.")):
                raise  # the module exists but its own import failed: not a moved name
    else:
        return "lerobot is not installed"
    rest = parts[cut:]
    for index, attribute in enumerate(rest):
        if hasattr(found_object, attribute):
            found_object = getattr(found_object, attribute)
        elif index == len(rest) - 1 and isinstance(found_object, type) and \
                attribute in _set_on_instances(found_object):
            return None
        else:
            return f"{'.'.join(parts[:cut + index])} has no {attribute}"
    return None


def unresolved(declared: Mapping[str, tuple[str, ...]]) -> list[str]:
    """A line per declared name (home -> names) the installed lerobot lacks, naming its home and why."""
    return [f"{label}: {name} ({why})" for label, names in declared.items() for name in names
            if (why := missing(name)) is not None]


def _reader_inputs(every: list[Home]) -> tuple[set[str], set[str]]:
    """graftcache's own private names, and every name declared as lerobot's."""
    return own_names(list(package_trees().values())), {_last(name) for home in every for name in home.declared}


def test_every_reach_into_lerobot_is_declared_by_its_home_and_every_declaration_is_reached() -> None:
    every = homes()
    assert sorted(file for home in every for file in home.sources) == \
        sorted(path.relative_to(FOLDER).as_posix() for path in FOLDER.rglob("*.py"))  # each file has one home
    own, lerobot = _reader_inputs(every)
    assert [line for home in every for line in undeclared(home, own, lerobot)] == []
    assert [line for home in every for line in stale(home, own, lerobot)] == []
    others = {(file, name) for home in every for file, _, name, _ in found(home, own, lerobot)}
    assert sorted(set(OTHERS) - others) == []  # no stale entry


def test_every_declared_reach_exists_in_the_installed_lerobot() -> None:
    assert unresolved({home.label: home.declared for home in homes()}) == []


def test_a_name_the_installed_lerobot_lacks_is_reported_with_its_backbone() -> None:
    evo1 = "lerobot.policies.evo1.modeling_evo1.Evo1Policy"
    declared = {
        "evo1": (f"{evo1}._prepare_state", f"{evo1}._renamed", "lerobot.policies.evo1.gone._helper"),
        "groot": ("lerobot.policies.groot.modeling_groot.GrootPolicy._groot_model",  # set on its instances
                  "lerobot.policies.groot.modeling_groot.GrootPolicy._groot_model.config", "torch.nn.Module._apply"),
    }
    assert unresolved(declared) == [
        f"evo1: {evo1}._renamed ({evo1} has no _renamed)",
        "evo1: lerobot.policies.evo1.gone._helper (lerobot.policies.evo1 has no gone)",
        "groot: lerobot.policies.groot.modeling_groot.GrootPolicy._groot_model.config "
        "(lerobot.policies.groot.modeling_groot.GrootPolicy has no _groot_model)",
        "groot: torch.nn.Module._apply (not lerobot's)"]


def test_an_undeclared_reach_and_a_stale_declaration_are_reported() -> None:
    source = """
from lerobot.policies.evo1.internvl3_embedder import _batched_pixel_values, IMAGENET_MEAN


def context(self, policy, batch):
    self._mine, policy._mine = 1, 2
    states, _ = policy._prepare_state(batch)
    return policy.model.action_head._prepare_context(states), policy._device
"""
    evo1 = "lerobot.policies.evo1.modeling_evo1.Evo1Policy"
    home = Home("evo1", {"evo1/adapter.py": source}, (f"{evo1}._prepare_state", f"{evo1}._device",
                                                      f"{evo1}._maybe_autocast"), ("_collect_image_batches",))
    own, lerobot = {"_mine", "_device"}, {"_device"}  # graftcache has a _device too: a declared name is found anyway
    assert undeclared(home, own, lerobot) == [
        "evo1/adapter.py:2: from lerobot.policies.evo1.internvl3_embedder import _batched_pixel_values (evo1 declares "
        "no _batched_pixel_values)",
        "evo1/adapter.py:8: policy.model.action_head._prepare_context (evo1 declares no _prepare_context)",
        "evo1/spec.py:0: SPEC.image_method (evo1 declares no _collect_image_batches)"]
    assert stale(home, own, lerobot) == [f"evo1: {evo1}._maybe_autocast declared, never reached"]
