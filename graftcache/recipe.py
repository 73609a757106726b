"""Sweep recipes: a TOML file (cli/*.toml) of encoders x suites x backbones x seeds + controls, read and
checked before anything runs (graftcache.sweep runs it).

Recipe keys (unknown keys are errors, so a typo never silently falls back to a default):

    name, dataset, results, cache, device, suites, seeds, controls, objective
    camera_map     "POLICY=CACHE,...": which dataset camera feeds each policy camera where the names differ
                   (graftcache/cameras.py); passed to every fit and native-tower extract
    [[backbones]]  name, policy ("tiny" = trained on `dataset` by train-tiny, else hub id or folder); each name once
    [[encoders]]   name, weights, random_init, seed
    [extract]      fields of ExtractRequest  } except those the recipe product sets (`recipe=False`): e.g. batch_size,
    [fit]          fields of FitRequest      } storage_dtype, frame_stride, grids; steps, lr, eval_frames, lora_rank;
    [train_tiny]   fields of TinyTrainConfig } steps, seed (backbones with policy = "tiny")
    [executor]     fields of ExecutorSettings: where extractions and cells run (executor = "ray", address,
                   gpus_per_task, ...); `graftcache sweep --executor ...` flags override them

[extract] grids (default ["unpooled"]: each encoder's own patch grid, pooled at read time to whatever a fit
reads) is for storing pooled grids as well or instead, e.g. ["unpooled", "4x4"] (graftcache.sweep.encoder_grids).

Every value is checked against the type of the request field it sets (a string where a number, list
or boolean belongs is an error naming file, section and key), and against its range and choices: each declared once,
on the field (graftcache/requests.py), as for the CLI's flags.

Relative paths in `dataset` are resolved against the recipe's folder when they exist there, so a
recipe in cli/ can name ../data/libero_sample; anything else is passed on (a hub repo id).
"""

from __future__ import annotations

import tomllib
import typing
from collections.abc import Mapping
from dataclasses import dataclass, field, fields, make_dataclass
from pathlib import Path
from typing import Any

from graftcache.backbone_registry import BACKBONES
from graftcache.cameras import parse_camera_map
from graftcache.codecs import matches, type_name
from graftcache.errors import GraftcacheError
from graftcache.fit.controls import get_control
from graftcache.requests import ExecutorSettings, ExtractRequest, FitRequest, TinyTrainConfig
from graftcache.settings import declared, recipe_keys, renamed


class RecipeError(GraftcacheError):
    """A sweep recipe that cannot be run as written (names the file and the key)."""


@dataclass(frozen=True)
class EncoderEntry:
    name: str
    weights: str | None = None
    random_init: bool = False
    seed: int = 0

    @property
    def label(self) -> str:
        return f"{self.name} (random-init, seed {self.seed})" if self.random_init else self.name


@dataclass(frozen=True)
class BackboneEntry:
    name: str
    policy: str = "tiny"


#: The request each settings section overrides; its own defaults apply to anything the section leaves out.
SECTIONS: dict[str, type] = {"extract": ExtractRequest, "fit": FitRequest, "train_tiny": TinyTrainConfig,
                             "executor": ExecutorSettings}
#: Settings a recipe's [extract] / [fit] / [train_tiny] / [executor] sections may set: every field of the request
#: but those the sweep sets from its product (dataset, encoder, backbone, seeds, ...; nor `shard`: a sweep needs whole
#: caches), as each field declares (graftcache/requests.py, `recipe=False`).
SECTION_KEYS: dict[str, tuple[str, ...]] = {section: recipe_keys(cls) for section, cls in SECTIONS.items()}


#: The FitRequest settings a recipe sets once, at its top level, for every fit of the sweep: Recipe takes their types
#: and defaults from their declarations (graftcache/requests.py); the extractions take dataset, device, cache too.
TOP_LEVEL = ("dataset", "results", "seeds", "controls", "objective", "camera_map", "cache", "device")
_REQUIRED = ("name", "dataset", "results", "suites", "backbones", "encoders", "seeds")


class _RecipeMethods:
    """What a Recipe does (its fields: `Recipe`)."""

    @property
    def executor_settings(self) -> ExecutorSettings:
        return ExecutorSettings(**self.executor)

    @property
    def n_fits(self) -> int:
        """(seed, control) cells the sweep visits: per encoder, the plain graft and every control."""
        return len(self.backbones) * len(self.encoders) * len(self.suites) * len(self.seeds) * (1 + len(self.controls))

    @property
    def n_rows(self) -> int:
        """Distinct results rows: controls that read the native tower's cache (native, native-graft) do
        not depend on the candidate encoder, so they make one row per (backbone, suite, seed)."""
        native = sum(get_control(c).native_cache for c in self.controls)
        per_seed = len(self.encoders) * (1 + len(self.controls) - native) + native
        return len(self.backbones) * len(self.suites) * len(self.seeds) * per_seed

    def fit_request(self, backbone: str, policy: str, encoder: str, suite: str, **resolved: Any) -> FitRequest:
        """The FitRequest of one (backbone, encoder, suite) of the recipe product: the top-level settings, the [fit]
        section, and what the sweep resolved (`resolved`: cache keys, ...)."""
        return FitRequest(backbone=backbone, policy=policy, encoder=encoder, suite=suite,
                          **{k: getattr(self, k) for k in TOP_LEVEL}, progress=False,
                          command=f"graftcache sweep {self.path}", **resolved, **self.fit)

    def extract_request(self, encoder: str, **kw: Any) -> ExtractRequest:
        """The ExtractRequest of one of the sweep's caches: the [extract] section, overridden by `kw`."""
        return ExtractRequest(dataset=self.dataset, encoder=encoder, device=self.device, cache=self.cache,
                              **{**self.extract, **kw})


def _top_level(name: str) -> tuple:
    """A Recipe field declared by the FitRequest field it sets: its type, and its default unless required."""
    d = declared(FitRequest)[name]
    hint = str if name in ("dataset",) else d.hint  # a sweep needs a dataset (FitRequest's may be None)
    return (name, hint) if name in _REQUIRED else (name, hint, field(default=d.default))


#: One sweep, as read from a TOML file: its name, product axes (suites, backbones, encoders, and seeds, controls,
#: objective among the TOP_LEVEL settings), and per-stage settings sections: request overrides.
Recipe = make_dataclass(
    "Recipe",
    [("name", str), *(_top_level(k) for k in TOP_LEVEL if k in _REQUIRED),
     ("suites", tuple[str, ...]), ("backbones", tuple[BackboneEntry, ...]), ("encoders", tuple[EncoderEntry, ...]),
     *(_top_level(k) for k in TOP_LEVEL if k not in _REQUIRED),
     ("extract", Mapping[str, Any], field(default_factory=dict)),     # ExtractRequest overrides
     ("fit", Mapping[str, Any], field(default_factory=dict)),         # FitRequest overrides
     ("train_tiny", Mapping[str, Any], field(default_factory=dict)),  # TinyTrainConfig overrides
     ("executor", Mapping[str, Any], field(default_factory=dict)),    # ExecutorSettings overrides
     ("path", str, field(default=""))],
    bases=(_RecipeMethods,), frozen=True, module=__name__)


_LISTS = {"backbones": BackboneEntry, "encoders": EncoderEntry}


def _typed(cls: type, values: Mapping[str, Any], where: str) -> dict[str, Any]:
    """`values` (TOML lists as tuples) after checking each against `cls`'s field types."""
    hints = typing.get_type_hints(cls)
    out = {k: _tuples(v) for k, v in values.items()}
    for key, value in out.items():
        if key in hints and not matches(value, hints[key]):
            raise RecipeError(f"{where}: {key} = {value!r} is not a {type_name(hints[key])}")
    return out


def _tuples(value: Any) -> Any:
    return tuple(_tuples(v) for v in value) if isinstance(value, list) else value


def _build(cls: type, data: Mapping[str, Any], where: str) -> Any:
    """A frozen dataclass from a recipe section; unknown, missing or mistyped keys name the place in the recipe."""
    known = {f.name for f in fields(cls)}
    unknown = sorted(set(data) - known)
    if unknown:
        raise RecipeError(f"{where}: unknown key(s) {', '.join(unknown)}; known: {', '.join(sorted(known))}")
    try:
        return cls(**_typed(cls, data, where))
    except TypeError as e:
        raise RecipeError(f"{where}: {e}") from None


def _section(data: Mapping[str, Any], section: str, where: str) -> dict[str, Any]:
    """A settings section as request overrides; keys outside SECTION_KEYS[section] or of the wrong type,
    and values the request refuses, name the place."""
    given = renamed(SECTIONS[section], data.get(section, {}), f"{where} [{section}]")
    unknown = sorted(set(given) - set(SECTION_KEYS[section]))
    if unknown:
        raise RecipeError(f"{where} [{section}]: unknown key(s) {', '.join(unknown)}; known: "
                          f"{', '.join(sorted(SECTION_KEYS[section]))}")
    cls = SECTIONS[section]
    values = _typed(cls, given, f"{where} [{section}]")
    try:
        cls.check(values)
    except GraftcacheError as e:
        raise RecipeError(f"{where} [{section}]: {e}") from None
    return values


def _resolve_dataset(dataset: str, recipe_dir: Path) -> str:
    candidate = recipe_dir / dataset
    return str(candidate.resolve()) if not Path(dataset).is_absolute() and candidate.exists() else dataset


def load_recipe(path: str | Path) -> Recipe:
    """Read and check a sweep recipe; errors name the file and the offending key."""
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise RecipeError(f"{path}: no such recipe file") from None
    except tomllib.TOMLDecodeError as e:
        raise RecipeError(f"{path}: not valid TOML ({e})") from None
    missing = [k for k in _REQUIRED if k not in data]
    if missing:
        raise RecipeError(f"{path}: missing key(s) {', '.join(missing)}")
    top = {k: v for k, v in data.items() if k not in SECTION_KEYS and k not in _LISTS}
    top["backbones"] = tuple(_build(BackboneEntry, b, f"{path} [[backbones]] #{i + 1}")
                             for i, b in enumerate(data["backbones"]))
    top["encoders"] = tuple(_build(EncoderEntry, e, f"{path} [[encoders]] #{i + 1}")
                            for i, e in enumerate(data["encoders"]))
    for section in SECTION_KEYS:
        top[section] = _section(data, section, str(path))
    top["dataset"] = _resolve_dataset(str(data["dataset"]), path.resolve().parent)
    recipe = _build(Recipe, {**top, "path": str(path)}, str(path))
    for control in recipe.controls:
        try:
            get_control(control)
        except GraftcacheError as e:
            raise RecipeError(f"{path}: controls: {e}") from None
    if recipe.camera_map is not None:
        try:
            parse_camera_map(recipe.camera_map)
        except GraftcacheError as e:
            raise RecipeError(f"{path}: camera_map: {e}") from None
    if not recipe.seeds or not recipe.suites or not recipe.encoders or not recipe.backbones:
        raise RecipeError(f"{path}: suites, seeds, encoders and backbones must each list at least one entry")
    _check_axes(recipe, path)
    return recipe


def _check_axes(recipe: Recipe, path: Path) -> None:
    """The product axes by the rules of the requests they become (seeds, suites, controls, objective: FitRequest's;
    an encoder's seed: ExtractRequest's), and no entry twice: a repeated seed, suite, encoder or backbone
    would visit its cells twice (each written once), so the counts the sweep reports would be wrong.

    Backbones are told apart by name alone, as the sweep keys its policies, token grids and native caches
    (graftcache.sweep.SweepState) and the report its rows (backbone, suite, encoder, control, seed): two
    entries of one name with different policies would have the last policy's cells computed for both."""
    for key, values in (("seeds", recipe.seeds), ("controls", recipe.controls), ("objective", recipe.objective)):
        _rule(FitRequest, key, values, str(path))
    for suite in recipe.suites:
        _rule(FitRequest, "suite", suite, f"{path}: suites")
    for i, enc in enumerate(recipe.encoders):
        _rule(ExtractRequest, "seed", enc.seed, f"{path} [[encoders]] #{i + 1}")
    for i, entry in enumerate(recipe.backbones):
        if entry.name not in BACKBONES:
            raise RecipeError(f"{path} [[backbones]] #{i + 1}: unknown backbone {entry.name!r}; known: "
                              f"{', '.join(BACKBONES)}")
    for key, entries in (("suites", recipe.suites), ("encoders", tuple(map(_same_cache, recipe.encoders))),
                         ("backbones", tuple(b.name for b in recipe.backbones))):
        first: dict[Any, int] = {}
        for i, entry in enumerate(entries):
            if entry in first:
                which = (f"suites lists {entry!r} twice" if key == "suites" else
                         f"#{first[entry] + 1} and #{i + 1} of [[{key}]] are the same")
                if key == "backbones" and recipe.backbones[first[entry]] != recipe.backbones[i]:
                    raise RecipeError(
                        f"{path}: #{first[entry] + 1} and #{i + 1} of [[backbones]] both name {entry!r} (policies "
                        f"{recipe.backbones[first[entry]].policy!r} and {recipe.backbones[i].policy!r}); a sweep "
                        "and its report key backbones by name: list each once (another policy: a recipe and "
                        "results file of its own)")
                raise RecipeError(f"{path}: {which}; list each once")
            first[entry] = i


def _same_cache(enc: EncoderEntry) -> tuple:
    """What decides an encoder entry's cache: its seed for random-init weights, else its weights."""
    return (enc.name, True, enc.seed) if enc.random_init else (enc.name, False, enc.weights)


def _rule(cls: type, key: str, value: Any, where: str) -> None:
    try:
        cls.check({key: value})
    except GraftcacheError as e:
        raise RecipeError(f"{where}: {e}") from None
