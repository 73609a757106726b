"""A sweep's checks before any work: whatever the real run would refuse later (after training a tiny policy,
after extracting), found from the recipe, the dataset's metadata and the encoders' specs alone.

`graftcache.sweep.check_sweep` runs `check_inputs`, then the checks that need the sweep's own logic;
`run_sweep` runs it first and `graftcache sweep --dry-run` runs it and stops, so a recipe the
dry run passes is not refused by these checks halfway through the real run. What it builds to check is what
the run builds: the ExtractRequest of every cache and the FitRequest of every (backbone, encoder, suite),
whose fields' rules apply (graftcache/requests.py); the suites' held-out split (graftcache.fit.data.split_episodes)
on the dataset's episodes; every encoder's spec and each extraction's memory (graftcache.extract.check_memory).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import polars as pl

from graftcache.backbone_registry import native_name
from graftcache.datasets import DatasetMeta, open_dataset, suite_of
from graftcache.encoders import get_spec
from graftcache.errors import GraftcacheError
from graftcache.extract import check_memory
from graftcache.fit.controls import check_pool_grid, get_control
from graftcache.fit.data import split_episodes
from graftcache.fit.objectives import reads_native
from graftcache.pooling import format_grid, resolve_grids
from graftcache.recipe import Recipe, RecipeError
from graftcache.requests import ExtractRequest, FitRequest
from graftcache.runtime import resolve_device


def check_inputs(recipe: Recipe) -> list[str]:
    """Raise the first thing the sweep would refuse; return what was found, a line each, for the dry run."""
    device = resolve_device(recipe.device)
    meta = open_dataset(recipe.dataset).meta  # missing, malformed, self-contradicting or empty: refused here
    extracts = [_extract_request(recipe, enc.name, weights=enc.weights, random_init=enc.random_init,
                                 seed=enc.seed) for enc in recipe.encoders]
    if reads_native(recipe.objective, recipe.controls):
        extracts += [_extract_request(recipe, native_name(b.name), camera_map=recipe.camera_map)
                     for b in recipe.backbones]
    fits = [_fit_request(recipe, backbone.name, backbone.policy, enc.name, suite)
            for backbone in recipe.backbones for enc in recipe.encoders for suite in recipe.suites]
    notes = [f"contents  {len(meta.episodes)} episodes, {meta.n_frames} frames, cameras "
             f"{', '.join(meta.cameras)}"]
    for suite, episodes in _suite_episodes(recipe, meta).items():
        fit = fits[0]  # the split depends on the suite and the [fit] settings alone
        try:
            split = split_episodes(episodes, eval_fraction=fit.eval_fraction, seed=fit.eval_split_seed,
                                   rule=fit.eval_split)
        except GraftcacheError as e:
            raise RecipeError(f"{recipe.path}: suite {suite!r} of {meta.root}: {e}") from None
        notes.append(f"suite     {suite}: {len(split.train_episodes)} train / {len(split.eval_episodes)} "
                     "held-out episodes")
    for req in extracts:
        spec = get_spec(req.encoder)  # an unknown encoder name is refused before any policy is trained
        if spec.library == "native":
            continue  # a native tower's grid and width are measured from its policy, which may not exist yet
        stored = resolve_grids(req.grids, spec.grid)
        try:  # a pool control far finer than the grids the cache will store: refused before it is extracted
            notes += filter(None, (check_pool_grid(get_control(c), stored, f"the cache of encoder {req.encoder}")
                                   for c in recipe.controls))
        except GraftcacheError as e:
            raise RecipeError(f"{recipe.path}: controls: {e}") from None
        grids = tuple(map(format_grid, stored))
        frames = sum(-(-e.length // req.frame_stride) for e in meta.episodes)
        check_memory(dataclasses.replace(req, grids=grids), meta, list(req.cameras or meta.cameras),
                     spec.width, frames, device)
    return notes


def _suite_episodes(recipe: Recipe, meta: DatasetMeta) -> dict[str, pl.DataFrame]:
    """Per recipe suite, its episodes (episode_index, task_index) in the dataset; one it lacks is an error."""
    suite_of_task = [suite_of(t) for t in meta.tasks]
    table = pl.DataFrame({"episode_index": [e.index for e in meta.episodes],
                          "task_index": [e.task_index for e in meta.episodes]})
    table = table.with_columns(
        pl.col("task_index").map_elements(lambda i: suite_of_task[i], return_dtype=pl.String).alias("suite"))
    out = {}
    for suite in recipe.suites:
        episodes = table.filter(pl.col("suite") == suite)
        if episodes.height == 0:
            present = sorted(set(table["suite"].to_list()))
            raise RecipeError(f"{recipe.path}: suites: dataset {meta.root} has no episode of {suite!r} "
                              f"(present: {', '.join(present)})")
        out[suite] = episodes
    return out


def _extract_request(recipe: Recipe, encoder: str, **kw: Any) -> ExtractRequest:
    return _made(recipe, "extract", lambda: recipe.extract_request(encoder, **kw))


def _fit_request(recipe: Recipe, backbone: str, policy: str, encoder: str, suite: str) -> FitRequest:
    return _made(recipe, "fit", lambda: recipe.fit_request(backbone, policy, encoder, suite))


def _made[R](recipe: Recipe, section: str, build: Callable[[], R]) -> R:
    """The request `build` makes, its refusal (a field's rule, a combination) naming the recipe and the section."""
    try:
        return build()
    except GraftcacheError as e:
        raise RecipeError(f"{recipe.path} [{section}]: {e}") from None
