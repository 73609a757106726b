"""Sweeps: a TOML recipe (cli/*.toml) of encoders x suites x backbones x seeds + controls, run as
missing caches first, then missing cells.

Everything a sweep does is an ordinary command underneath (`train-tiny`, `extract`, `fit`), so each
step reuses what exists: complete caches are found by key, trained tiny backbones by dataset and
recipe, and finished cells by `run_id` in the results file. Rerunning a sweep after an interruption
therefore continues where it stopped, and rerunning a finished one only reads.

Recipe keys (unknown keys are errors, so a typo never silently falls back to a default):

    name, dataset, results, cache, device, suites, seeds, controls, objective
    [[backbones]]  name, policy ("tiny" = natively trained on `dataset`, else hub id or folder)
    [[encoders]]   name, weights, random_init, seed
    [extract]      batch_size, num_workers, dtype, compute_dtype, cameras, block_frames, frame_stride
    [fit]          steps, lr, batch_size, eval_fraction, eval_split_seed, eval_frames, num_denoise_steps,
                   lora_rank, compute_dtype, out
    [train_tiny]   steps, batch_size, lr, weight_decay, seed, image_size, warmup, compute_dtype
                   (backbones with policy = "tiny")

Every value is checked against the type of the request field it sets (a string where a number, list
or boolean belongs is an error naming file, table and key), and the requests check their ranges.

Relative paths in `dataset` are resolved against the recipe's folder when they exist there, so a
recipe in cli/ can name ../data/libero_sample; anything else is passed on (a hub repo id).
"""

from __future__ import annotations

import dataclasses
import tomllib
import types
import typing
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

from graftcache.backbones.pool import BackbonePool
from graftcache.errors import GraftcacheError
from graftcache.fit.controls import get_control
from graftcache.pooling import format_grid
from graftcache.progress import progress, write


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


#: Settings a recipe's [extract] / [fit] / [train_tiny] tables may set: fields of the request the sweep
#: builds (ExtractRequest, FitRequest, TinyTrainConfig), whose own defaults apply to anything left out.
#: The rest of each request (dataset, encoder, backbone, seeds, ...) comes from the grid itself.
SECTION_KEYS: dict[str, tuple[str, ...]] = {
    "extract": ("batch_size", "num_workers", "dtype", "compute_dtype", "cameras", "block_frames", "frame_stride"),
    "fit": ("steps", "lr", "batch_size", "eval_fraction", "eval_split_seed", "eval_frames", "num_denoise_steps",
            "lora_rank", "compute_dtype", "out", "accept_numerics_drift"),
    "train_tiny": ("steps", "batch_size", "lr", "weight_decay", "seed", "image_size", "warmup", "compute_dtype"),
}


@dataclass(frozen=True)
class Recipe:
    """One sweep, as read from a TOML file."""

    name: str
    dataset: str
    results: str
    suites: tuple[str, ...]
    backbones: tuple[BackboneEntry, ...]
    encoders: tuple[EncoderEntry, ...]
    seeds: tuple[int, ...]
    controls: tuple[str, ...] = ()
    objective: str = "flow"
    cache: str | None = None
    device: str = "cpu"
    extract: Mapping[str, Any] = field(default_factory=dict)     # ExtractRequest overrides
    fit: Mapping[str, Any] = field(default_factory=dict)         # FitRequest overrides
    train_tiny: Mapping[str, Any] = field(default_factory=dict)  # TinyTrainConfig overrides
    path: str = ""

    @property
    def n_fits(self) -> int:
        """(seed, control) cells the sweep visits: per encoder, the plain graft and every control."""
        return len(self.backbones) * len(self.encoders) * len(self.suites) * len(self.seeds) * (1 + len(self.controls))

    @property
    def n_rows(self) -> int:
        """Distinct results rows: controls that read the native tower's cache (native, native-graft) do
        not depend on the candidate encoder, so they make one row per (backbone, suite, seed)."""
        native = sum(get_control(c).uses_native_cache for c in self.controls)
        per_seed = len(self.encoders) * (1 + len(self.controls) - native) + native
        return len(self.backbones) * len(self.suites) * len(self.seeds) * per_seed


_LISTS = {"backbones": BackboneEntry, "encoders": EncoderEntry}
_REQUIRED = ("name", "dataset", "results", "suites", "backbones", "encoders", "seeds")


def _matches(value: Any, hint: Any) -> bool:
    """Whether a TOML value (lists already turned into tuples) fits a dataclass field's type hint."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if hint is Any:
        return True
    if origin in (typing.Union, types.UnionType):
        return any(_matches(value, a) for a in args)
    if hint is type(None):
        return value is None
    if origin is tuple:
        if not isinstance(value, tuple):
            return False
        if len(args) == 2 and args[1] is Ellipsis:
            return all(_matches(v, args[0]) for v in value)
        return len(args) == len(value) and all(_matches(v, a) for v, a in zip(value, args))
    if origin is not None:  # Mapping[...], dict[...]
        return isinstance(value, origin)
    if hint is float:
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    if hint is int:
        return isinstance(value, int) and not isinstance(value, bool)
    return isinstance(value, hint)


def _type_name(hint: Any) -> str:
    return getattr(hint, "__name__", None) or str(hint).replace("typing.", "")


def _typed(cls: type, values: Mapping[str, Any], where: str) -> dict[str, Any]:
    """`values` (TOML lists as tuples) after checking each against `cls`'s field types."""
    hints = typing.get_type_hints(cls)
    out = {k: _tuples(v) for k, v in values.items()}
    for key, value in out.items():
        if key in hints and not _matches(value, hints[key]):
            raise RecipeError(f"{where}: {key} = {value!r} is not a {_type_name(hints[key])}")
    return out


def _tuples(value: Any) -> Any:
    return tuple(_tuples(v) for v in value) if isinstance(value, list) else value


def _build(cls: type, data: Mapping[str, Any], where: str) -> Any:
    """A frozen dataclass from a TOML table; unknown, missing or mistyped keys name the place in the recipe."""
    known = {f.name for f in fields(cls)}
    unknown = sorted(set(data) - known)
    if unknown:
        raise RecipeError(f"{where}: unknown key(s) {', '.join(unknown)}; known: {', '.join(sorted(known))}")
    try:
        return cls(**_typed(cls, data, where))
    except TypeError as e:
        raise RecipeError(f"{where}: {e}") from None


def _section_classes() -> dict[str, type]:
    """The request each settings table overrides (imported on use: they pull in torch)."""
    from graftcache.extract import ExtractRequest
    from graftcache.fit.run import FitRequest
    from graftcache.pretrain import TinyTrainConfig

    return {"extract": ExtractRequest, "fit": FitRequest, "train_tiny": TinyTrainConfig}


def _section(data: Mapping[str, Any], section: str, where: str) -> dict[str, Any]:
    """A settings table as request overrides; keys outside SECTION_KEYS[section] or of the wrong type,
    and values the request refuses, name the place."""
    table = data.get(section, {})
    unknown = sorted(set(table) - set(SECTION_KEYS[section]))
    if unknown:
        raise RecipeError(f"{where} [{section}]: unknown key(s) {', '.join(unknown)}; known: "
                          f"{', '.join(sorted(SECTION_KEYS[section]))}")
    cls = _section_classes()[section]
    values = _typed(cls, table, f"{where} [{section}]")
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
    if not recipe.seeds or not recipe.suites or not recipe.encoders or not recipe.backbones:
        raise RecipeError(f"{path}: suites, seeds, encoders and backbones must each list at least one entry")
    return recipe


# ------------------------------------------------------------------------------------------- running
@dataclass
class SweepState:
    """What the sweep resolved on the way: policy folders, native grids, cache keys."""

    policies: dict[str, str] = field(default_factory=dict)           # backbone -> policy folder / id
    native_grids: dict[str, tuple[int, int]] = field(default_factory=dict)
    encoder_caches: dict[EncoderEntry, str] = field(default_factory=dict)
    native_caches: dict[str, str] = field(default_factory=dict)      # backbone -> native tower cache key
    commands: dict[str, str] = field(default_factory=dict)           # what produced each cache / policy


def _needs_native(recipe: Recipe) -> bool:
    return recipe.objective == "align" or any(get_control(c).uses_native_cache for c in recipe.controls)


def _pool_grids(recipe: Recipe) -> list[tuple[int, int]]:
    return [g for g in (get_control(c).grid for c in recipe.controls) if g is not None]


def prepare_policies(recipe: Recipe, state: SweepState, log: Callable[[str], None]) -> None:
    """Train (or reuse) tiny backbones, then read each backbone's native token grid from its config."""
    from graftcache.backbones import get_backbone
    from graftcache.pretrain import DEFAULT_TINY_TRAIN, train_tiny

    for entry in recipe.backbones:
        policy = entry.policy
        if policy == "tiny":
            cfg = dataclasses.replace(DEFAULT_TINY_TRAIN, **recipe.train_tiny)
            policy = str(train_tiny(entry.name, recipe.dataset, cfg=cfg, cache=recipe.cache, device=recipe.device,
                                    log=log))
            state.commands[f"policy {entry.name}"] = (f"graftcache train-tiny --backbone {entry.name} "
                                                     f"--dataset {recipe.dataset} --steps {cfg.steps}")
        state.policies[entry.name] = policy
        state.native_grids[entry.name] = get_backbone(entry.name).read_native_grid(policy)


def _extract(recipe: Recipe, encoder: str, grids: list[tuple[int, int]], log: Callable[[str], None], **kw: Any) -> str:
    from graftcache.extract import ExtractRequest, extract

    req = ExtractRequest(dataset=recipe.dataset, encoder=encoder, grids=tuple(dict.fromkeys(grids)),
                         device=recipe.device, cache=recipe.cache, **recipe.extract, **kw)
    return extract(req, log=log).key


def prepare_caches(recipe: Recipe, state: SweepState, log: Callable[[str], None]) -> None:
    """Extract every encoder at every grid the grid of fits reads, plus the native towers if needed."""
    grids = sorted(set(state.native_grids.values()) | set(_pool_grids(recipe)))
    grid_text = ",".join(format_grid(g) for g in grids)
    for enc in recipe.encoders:
        state.encoder_caches[enc] = _extract(recipe, enc.name, grids, log, weights=enc.weights,
                                             random_init=enc.random_init, seed=enc.seed)
        flags = " --random-init --seed {}".format(enc.seed) if enc.random_init else (
            f" --weights {enc.weights}" if enc.weights else "")
        state.commands[state.encoder_caches[enc]] = (f"graftcache extract --encoder {enc.name}{flags} "
                                                     f"--dataset {recipe.dataset} --grids {grid_text}")
    if not _needs_native(recipe):
        return
    from graftcache.backbones.native import native_name

    for backbone, policy in state.policies.items():
        grid = state.native_grids[backbone]
        key = _extract(recipe, native_name(backbone), [grid], log, policy=policy)
        state.native_caches[backbone] = key
        state.commands[key] = (f"graftcache extract --encoder {native_name(backbone)} --policy {policy} "
                               f"--dataset {recipe.dataset} --grids {format_grid(grid)}")


def fit_requests(recipe: Recipe, state: SweepState) -> Iterator[tuple[str, Any]]:
    """(label, FitRequest) per (backbone, encoder, suite), all seeds in one request so that the cached
    features are read once per request, in a stable order."""
    from graftcache.fit.run import FitRequest

    for backbone in recipe.backbones:
        for enc in recipe.encoders:
            for suite in recipe.suites:
                yield f"{backbone.name}/{enc.label}/{suite}", FitRequest(
                    backbone=backbone.name, encoder=enc.name, suite=suite, policy=state.policies[backbone.name],
                    dataset=recipe.dataset, cache_key=state.encoder_caches[enc],
                    native_cache_key=state.native_caches.get(backbone.name), seeds=recipe.seeds,
                    controls=recipe.controls, objective=recipe.objective, device=recipe.device,
                    results=recipe.results, cache=recipe.cache, progress=False,
                    command=f"graftcache sweep {recipe.path}", **recipe.fit)


def run_sweep(recipe: Recipe, log: Callable[[str], None] = write) -> SweepState:
    """Policies, then caches, then every missing cell; one progress bar over the grid's rows."""
    from graftcache.fit.run import Fitter

    state, backbones = SweepState(), BackbonePool(log)
    log(f"sweep {recipe.name}: {len(recipe.backbones)} backbone(s) x {len(recipe.encoders)} encoder(s) x "
        f"{len(recipe.suites)} suite(s) x {len(recipe.seeds)} seed(s) x {1 + len(recipe.controls)} control(s) "
        f"= {recipe.n_fits} cells, {recipe.n_rows} distinct rows -> {recipe.results}")
    prepare_policies(recipe, state, log)
    prepare_caches(recipe, state, log)
    per_request = len(recipe.seeds) * (1 + len(recipe.controls))
    with progress(total=recipe.n_fits, desc=f"sweep {recipe.name}", unit="cell") as bar:
        for label, req in fit_requests(recipe, state):
            bar.set_postfix_str(label)
            Fitter(req, log=log, backbones=backbones).run()
            bar.update(per_request)
    return state
