"""Sweeps: a recipe (graftcache.recipe) run as missing caches first, then missing cells.

Everything a sweep does is an ordinary command underneath (`train-tiny`, `extract`, `fit`), so each
step reuses what exists: complete caches are found by key, trained tiny backbones by dataset and
recipe, and finished cells by `run_id` in the results file. Rerunning a sweep after an interruption
therefore continues where it stopped, and rerunning a finished one only reads. What produced each cache
and policy is kept as the equivalent command line, for the report.

Each encoder is extracted once, at its own patch grid (`extract --grids unpooled`) unless the recipe's [extract]
section names `grids`: one cache serves every backbone, pool control and the align objective, each pooled from
it at read time (graftcache.fit.data.read_grid). A native tower's cache serves its own backbone only, so it
stores that backbone's token grid, the one grid its controls read (a released SmolVLA tower's own grid is
32x32, sixteen times the 8x8 that native-graft reads).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

from graftcache.backbone_registry import native_name
from graftcache.cameras import match_cameras
from graftcache.errors import GraftcacheError
from graftcache.executors import Executor, get_executor
from graftcache.fit.controls import get_control
from graftcache.fit.objectives import reads_native
from graftcache.pooling import UNPOOLED, format_grid, grid_names
from graftcache.progress import progress, write
from graftcache.recipe import EncoderEntry, Recipe
from graftcache.requests import DEFAULT_TINY_TRAIN, ExecutorSettings, ExtractRequest, TinyTrainConfig
from graftcache.settings import write_flags


def command_line(command: str, request: type, **values: Any) -> str:
    """`graftcache <command> --flag value ...`: `values`, fields of `request`, as the flags that set them, each
    written as its field's codec writes it (graftcache.settings.write_flags), so the line parses back to them."""
    return " ".join([f"graftcache {command}", *write_flags(request, values)])


@dataclass
class SweepState:
    """What the sweep resolved on the way: policy folders, token grids, cache keys."""

    policies: dict[str, str] = field(default_factory=dict)           # backbone -> policy folder / id
    token_grids: dict[str, tuple[int, int]] = field(default_factory=dict)
    encoder_caches: dict[EncoderEntry, str] = field(default_factory=dict)
    native_caches: dict[str, str] = field(default_factory=dict)      # backbone -> native tower cache key
    commands: dict[str, str] = field(default_factory=dict)           # what produced each cache / policy


def _pool_grids(recipe: Recipe) -> list[tuple[int, int]]:
    return [g for g in (get_control(c).grid for c in recipe.controls) if g is not None]


def prepare_policies(recipe: Recipe, state: SweepState, log: Callable[[str], None]) -> None:
    """Train (or reuse) tiny backbones, then read each backbone's token grid from its config."""
    from graftcache.backbones import get_backbone
    from graftcache.pretrain import train_tiny

    for entry in recipe.backbones:
        policy = entry.policy
        if policy == "tiny":
            cfg = dataclasses.replace(DEFAULT_TINY_TRAIN, **recipe.train_tiny)
            policy = str(train_tiny(entry.name, recipe.dataset, cfg=cfg, cache=recipe.cache, device=recipe.device,
                                    log=log))
            state.commands[f"policy {entry.name}"] = command_line(
                "train-tiny", TinyTrainConfig, backbone=entry.name, dataset=recipe.dataset, steps=cfg.steps,
                cameras=cfg.cameras)
        state.policies[entry.name] = policy
        state.token_grids[entry.name] = get_backbone(entry.name).read_token_grid(policy)
    check_cameras(recipe, state)


def check_cameras(recipe: Recipe, state: SweepState) -> None:
    """Every policy's cameras against those its caches will hold (the recipe's [extract] cameras, else the
    dataset's), by name or as the recipe's camera_map says, before anything is extracted: a mismatch found by
    the first fit would come after every extraction."""
    from graftcache.backbones import get_backbone
    from graftcache.datasets import open_dataset

    cameras = recipe.extract.get("cameras") or open_dataset(recipe.dataset).meta.cameras
    for backbone, policy in state.policies.items():
        match_cameras(get_backbone(backbone).read_cameras(policy), cameras, recipe.camera_map, policy_name=policy,
                      cache_name=f"dataset {recipe.dataset}")


def _extract(recipe: Recipe, executor: Executor, encoder: str, grids: tuple[str, ...], log: Callable[[str], None],
             **kw: Any) -> str:
    req = recipe.extract_request(encoder, grids=grids, **kw)
    return executor.extract(req, log).key


def _extract_settings(recipe: Recipe, grids: tuple[str, ...]) -> dict[str, Any]:
    """The recipe's [extract] section with the grids a cache stores: request fields, and the command's flags."""
    return {**recipe.extract, "grids": grids}


def encoder_grids(recipe: Recipe, state: SweepState) -> tuple[str, ...]:
    """The grids every encoder's cache stores: the recipe's [extract] grids, by default the encoder's own grid
    alone. Explicit grids without `unpooled` must include every grid the fits read (each backbone's token grid
    and each pool control's): pooling a coarser stored grid up to one of them would only repeat cells."""
    names = grid_names(",".join(recipe.extract.get("grids", ExtractRequest.grids)))
    if UNPOOLED not in names:
        read = sorted(set(state.token_grids.values()) | set(_pool_grids(recipe)))
        missing = [format_grid(g) for g in read if format_grid(g) not in names]
        if missing:
            raise GraftcacheError(f"{recipe.path} [extract]: grids = {list(names)} lacks {', '.join(missing)}, which "
                                  f"the fits read; add them, or {UNPOOLED!r} to pool them from the encoder's own grid")
    return names


def prepare_caches(recipe: Recipe, state: SweepState, log: Callable[[str], None], executor: Executor) -> None:
    """Extract every encoder once (`encoder_grids`), plus the native towers at their backbones' token grids
    if a control or the objective needs them."""
    grids = encoder_grids(recipe, state)
    for enc in recipe.encoders:
        state.encoder_caches[enc] = _extract(recipe, executor, enc.name, grids, log, weights=enc.weights,
                                             random_init=enc.random_init, seed=enc.seed)
        state.commands[state.encoder_caches[enc]] = command_line(
            "extract", ExtractRequest, encoder=enc.name, random_init=enc.random_init,
            seed=enc.seed if enc.random_init else None, weights=None if enc.random_init else enc.weights,
            dataset=recipe.dataset,
            **_extract_settings(recipe, grids))
    if not reads_native(recipe.objective, recipe.controls):
        return
    for backbone, policy in state.policies.items():
        grid = (format_grid(state.token_grids[backbone]),)
        key = _extract(recipe, executor, native_name(backbone), grid, log, policy=policy,
                       camera_map=recipe.camera_map)
        state.native_caches[backbone] = key
        state.commands[key] = command_line("extract", ExtractRequest, encoder=native_name(backbone), policy=policy,
                                           dataset=recipe.dataset, camera_map=recipe.camera_map,
                                           **_extract_settings(recipe, grid))


def fit_requests(recipe: Recipe, state: SweepState) -> Iterator[tuple[str, Any]]:
    """(label, FitRequest) per (backbone, encoder, suite), all seeds in one request so that the cached
    features are read once per request, in a stable order."""
    for backbone in recipe.backbones:
        for enc in recipe.encoders:
            for suite in recipe.suites:
                yield f"{backbone.name}/{enc.label}/{suite}", recipe.fit_request(
                    backbone.name, state.policies[backbone.name], enc.name, suite,
                    cache_key=state.encoder_caches[enc], native_cache_key=state.native_caches.get(backbone.name))


def check_sweep(recipe: Recipe) -> list[str]:
    """Everything the sweep would refuse on its way, before its first step (graftcache.preflight.check_inputs),
    then what needs a policy's config, for the policies that are checkpoints (tiny ones are not trained yet):
    their cameras (`check_cameras`) and, when every policy is one, the grids the caches store against each
    backbone's token grid (`encoder_grids`). Returns what was found, a line each, for `--dry-run`."""
    from graftcache.backbones import get_backbone
    from graftcache.preflight import check_inputs

    notes = check_inputs(recipe)
    read = [b for b in recipe.backbones if b.policy != "tiny"]  # a missing checkpoint is refused here
    state = SweepState(policies={b.name: b.policy for b in read},
                       token_grids={b.name: get_backbone(b.name).read_token_grid(b.policy) for b in read})
    check_cameras(recipe, state)
    if len(read) == len(recipe.backbones):
        encoder_grids(recipe, state)
    return notes


def run_sweep(recipe: Recipe, log: Callable[[str], None] = write,
              settings: ExecutorSettings | None = None) -> SweepState:
    """Policies, then caches, then every missing cell, on the executor `settings` name (default: the recipe's
    [executor] section); one progress bar over the recipe's cells."""
    check_sweep(recipe)  # what a later step would refuse, refused before the first (what --dry-run runs)
    settings = settings or recipe.executor_settings
    executor = get_executor(settings)
    state = SweepState()
    log(f"sweep {recipe.name}: {len(recipe.backbones)} backbone(s) x {len(recipe.encoders)} encoder(s) x "
        f"{len(recipe.suites)} suite(s) x {len(recipe.seeds)} seed(s) x {1 + len(recipe.controls)} control(s) "
        f"= {recipe.n_fits} cells, {recipe.n_rows} distinct rows -> {recipe.results} ({settings.executor} executor)")
    prepare_policies(recipe, state, log)
    prepare_caches(recipe, state, log, executor)
    with progress(total=recipe.n_fits, desc=f"sweep {recipe.name}", unit="cell") as bar:
        executor.fit(list(fit_requests(recipe, state)), log, bar)
    return state
