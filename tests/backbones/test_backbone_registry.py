"""The backbone registry is the folders of graftcache/backbones/: every registered backbone has every required piece
(graftcache.backbone_registry.PIECES: its adapter class, its tiny configuration), found by convention."""

from __future__ import annotations

import dataclasses
import inspect
import types
from importlib import import_module
from pathlib import Path

import pytest

from graftcache.backbone_registry import BACKBONES, FOLDER, PIECES, backbone_module, discover, missing_pieces
from graftcache.backbones import get_backbone, registered_spec
from graftcache.backbones.activation_checkpointing import ActivationCheckpointing
from graftcache.backbones.attention import Attention
from graftcache.backbones.base import BackboneAdapter
from graftcache.backbones.policy_loss import FlowLoss, PolicyLoss, TokenLoss
from graftcache.backbones.spec import BackboneSpec
from graftcache.errors import BackboneError


def test_the_registry_lists_the_folders_holding_an_adapter(tmp_path: Path) -> None:
    """Discovery on a made-up package folder: a folder with an adapter.py is a backbone, whatever else it lacks
    (the next test names its missing pieces); a folder without one, a module and a cache folder are not."""
    for folder, files in {"alpha": ("adapter.py",), "beta": ("adapter.py", "spec.py", "tiny.py"),
                          "shared": ("tiny.py",), "__pycache__": ("adapter.cpython-313.pyc",)}.items():
        (tmp_path / folder).mkdir()
        for name in files:
            (tmp_path / folder / name).write_text("")
    (tmp_path / "adapter.py").write_text("")
    assert discover(tmp_path) == {"alpha": "graftcache.backbones.alpha.adapter",
                                  "beta": "graftcache.backbones.beta.adapter"}
    assert {"smolvla", "pi05"} <= set(BACKBONES) and "tiny" not in BACKBONES  # the package's own: folders, not modules


def test_a_folder_lacking_a_piece_is_named(tmp_path: Path) -> None:
    (tmp_path / "adapter.py").write_text("")
    assert missing_pieces(tmp_path) == [p for p in PIECES if p != "adapter"]


@pytest.mark.parametrize("name", sorted(BACKBONES))
def test_every_registered_backbone_has_every_piece(name: str) -> None:
    assert missing_pieces(FOLDER / name) == [], f"graftcache/backbones/{name}/ lacks a required piece"
    adapter = get_backbone(name)
    assert issubclass(adapter, BackboneAdapter) and not inspect.isabstract(adapter), adapter.__abstractmethods__
    assert adapter.spec is registered_spec(name)  # what reports read without the adapter is what it runs with
    assert callable(import_module(backbone_module(name, "tiny")).build_tiny)


@pytest.mark.parametrize("name", sorted(BACKBONES))
def test_every_registered_backbone_declares_a_spec_its_hooks_agree_with(name: str) -> None:
    adapter = get_backbone(name)
    spec = adapter.spec
    assert isinstance(spec, BackboneSpec)
    assert spec.can_recompute == (
        adapter._switch_recompute is not ActivationCheckpointing._switch_recompute)
    assert (len(spec.attentions) > 1) == (adapter._switch_attention is not Attention._switch_attention)
    assert (spec.flow_time is None) == issubclass(adapter, TokenLoss)
    assert issubclass(adapter, FlowLoss) or "_flow_losses" not in dir(adapter)  # no flow loss that only raises
    assert spec.steps_field is not None or adapter.num_steps is not PolicyLoss.num_steps
    assert all(n >= 1 for n in spec.cells_per_pass.values())


def test_a_class_naming_itself_a_backbone_elsewhere_or_without_a_spec_of_its_own_is_refused() -> None:
    """BackboneAdapter.__init_subclass__: the registry's rules hold as an adapter class is defined."""
    smolvla = get_backbone("smolvla")

    def define(qualname: str, module: str, **body) -> type:
        return types.new_class(qualname, (smolvla,), exec_body=lambda ns: ns.update(__module__=module, **body))

    with pytest.raises(BackboneError, match=r"is defined in graftcache\.backbones\.stray\.adapter"):
        define("Stray", "tests.elsewhere", name="stray", spec=smolvla.spec)
    with pytest.raises(BackboneError, match=r"its `spec` is not graftcache\.backbones\.smolvla\.spec\.SPEC"):
        define("Inherits", backbone_module("smolvla"), name="smolvla")
    with pytest.raises(BackboneError, match=r"its `spec` is not graftcache\.backbones\.smolvla\.spec\.SPEC"):
        define("Copied", backbone_module("smolvla"), name="smolvla", spec=dataclasses.replace(smolvla.spec))
    assert define("Helper", "tests.elsewhere").spec is smolvla.spec  # no name of its own: not a registry entry
    assert smolvla.lerobot_type() == "smolvla"  # the registry name unless its spec names another lerobot type


@pytest.mark.parametrize("name", sorted(BACKBONES))
def test_the_spec_refuses_what_the_backbone_cannot_run_before_it_loads(name: str) -> None:
    """An attention path the spec does not list, a recompute plan without `can_recompute`, `--compile` without a
    compiled forward: refused from the spec's data, with the lines the adapter gives once loaded. mlp is refused
    from the spec only where the backbone cannot recompute at all: every adapter with MLP slots can."""
    spec, adapter = registered_spec(name), get_backbone(name)
    ok = {"attention": "auto", "recompute": "off", "compile": False}
    spec.check_execution(name, **ok)
    if adapter._mlp_slots is not ActivationCheckpointing._mlp_slots:
        assert spec.can_recompute
    for field, value, refused in (
            ("attention", "sdpa", "sdpa" not in spec.attentions),
            ("attention", "eager", "eager" not in spec.attentions),
            ("recompute", "on", not spec.can_recompute), ("recompute", "mlp", not spec.can_recompute),
            ("compile", True, spec.compiled_forward is None)):
        if not refused:
            spec.check_execution(name, **{**ok, field: value})
            continue
        with pytest.raises(BackboneError) as said:
            spec.check_execution(name, **{**ok, field: value})
        if field == "attention":
            with pytest.raises(BackboneError) as loaded:
                adapter.resolve_attention(value)
            assert str(said.value) == str(loaded.value)


def test_fit_refuses_evo1_s_sdpa_recompute_and_compile_before_loading(tmp_path: Path, capsys,
                                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    """They were refused after ~20 s of loading the policy and printing its parameter table."""
    from helpers.probes import run_cli

    from graftcache.fit import plan

    def load(*args: object, **kwargs: object) -> None:
        raise AssertionError("the backbone was looked up")

    monkeypatch.setattr(plan, "get_backbone", load)
    fit = ["fit", "--backbone", "evo1", "--policy", "tiny", "--encoder", "resnet18", "--dataset", tmp_path / "none",
           "--suite", "libero_spatial", "--cache", tmp_path / "cache", "--results", tmp_path / "r.parquet"]
    for flags, said in ((["--attention", "sdpa"], "attention 'sdpa' is not one of this backbone's (eager: lerobot's "
                         "own is eager); use --attention auto"),
                        (["--recompute", "mlp"], "no recompute plan 'mlp' for this backbone; use --recompute off"),
                        (["--recompute", "on"], "no recompute plan 'on' for this backbone; use --recompute off"),
                        (["--compile"], "no compiled forward for this backbone (its spec names none); drop --compile")):
        refused = run_cli([*fit, *flags], capsys)
        assert (refused.code, refused.err) == (2, f"graftcache fit: error: evo1: {said}\n"), flags
    assert not (tmp_path / "cache").exists()
