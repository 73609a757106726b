"""One fit, top to bottom: caches -> cells (seed x control) -> one results row per cell.

A cell is fitted against the frozen policy, loaded once per run and reset to its pristine state
between cells (graft surgery mutates it), from cached features only. Finished cells (same run_id in
the results file) are skipped before anything is loaded, so reruns and sweeps resume where they
stopped and a finished grid only reads. The projector of every trained cell is saved as safetensors
with a JSON sidecar in the run folder.

Cells that can share a pass of the frozen backbone (seeds, image controls, encoders of one grid and width) run
`cells_per_pass` to a pass, each training its own projector (graftcache/fit/passes.py).

The parts a cell is made of are registries: its control (fit/controls.py: which cache, which projector,
which feature transform) and its objective (fit/objectives.py: how the projector is fitted).
"""

from __future__ import annotations

import dataclasses
import functools
import json
import os
import time
from collections.abc import Callable, Mapping, Sequence
from contextlib import ExitStack, closing
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import polars as pl
import torch
from safetensors.torch import save_file

import graftcache
from graftcache import results
from graftcache.backbone_table import native_name
from graftcache.backbones import get_backbone
from graftcache.backbones.checkpoint import follow_umask
from graftcache.backbones.pool import BackbonePool
from graftcache.backbones.tiny_record import resolve_policy
from graftcache.cameras import format_camera_map, match_cameras, renames
from graftcache.encoders.fingerprint import NumericsCheck, check_numerics
from graftcache.errors import FitError
from graftcache.fit.buffer import MIB
from graftcache.fit.controls import Control, check_pool_grid, get_control
from graftcache.fit.data import LowDim, drop_nonfinite, load_lowdim, split_episodes, suite_index_table
from graftcache.fit.feed import SplitFeed
from graftcache.fit.lookup import find_cache
from graftcache.fit.loop import Scoring, evaluate, evaluate_together, learner, optimise_together
from graftcache.fit.objectives import EVAL_ONLY, OBJECTIVES, Fitting, Objective, flow_buffer
from graftcache.fit.passes import Member, default_cells_per_pass, run_passes
from graftcache.fit.step_memory import check_step_memory
from graftcache.fit.stream import BlockMemo, CacheReader, FeatureSource, StreamStats, read_blocks
from graftcache.graft import FusedProjector
from graftcache.pooling import format_grid, parse_grid
from graftcache.requests import FitRequest
from graftcache.runtime import resolve_compute_dtype, resolve_device, resolve_dtype
from graftcache.store import FeatureCache, cache_root
from graftcache.store.readthrough import ReadThroughRoot, reading_root

__all__ = ["Cell", "FitRequest", "Fitter"]


@dataclass(frozen=True)
class Cell:
    """What identifies one results row: every field, by name and value, is hashed into the row's run_id, with the
    shape of cells (`format_version`: results.CELL_FORMAT); a change of its shape is a new results.FORMAT_VERSION,
    whose results.upgrade says what becomes of older rows. A field added since CELL_FORMAT is hashed only where it
    differs from what every cell of that format held (results.FORMAT_3_VALUES), so that a cell format 3 could
    express keeps its run_id."""

    backbone: str
    policy: str
    cache_key: str
    suite: str
    seed: int
    control: str
    pool_grid: str            # the grid its features are pooled to, resolved ("8x8": the control's, else the
                              # backbone's token grid), so that the run_id hashes what the row writes
    objective: str            # "flow" | "align" | "align-flow" | "eval"
    steps: int
    lr: float
    batch_size: int
    buffer_mib: int
    lora_rank: int
    eval_fraction: float
    eval_split_seed: int
    eval_frames: int | None
    num_denoise_steps: int | None
    compute_dtype: str
    camera_map: str | None = None  # canonical text, only when a policy camera is fed by another name
    eval_split: str = "graftcache"  # which episodes are held out (graftcache.fit.data.SPLITS)
    format_version: int = results.CELL_FORMAT

    @property
    def run_id(self) -> str:
        known = results.FORMAT_3_VALUES
        return results.make_run_id({k: v for k, v in asdict(self).items() if not (k in known and known[k] == v)})

    def row(self, req: FitRequest, measured: Mapping[str, Any]) -> dict[str, Any]:
        """The results row: each SCHEMA column from what the cell measured, else the cell, else the request
        (so a new column that names a request field needs no code here)."""
        sources = (measured, asdict(self), asdict(req))
        row = {}
        for column in results.SCHEMA:
            source = next((s for s in sources if column in s), None)
            if source is None:
                raise FitError(f"results column {column!r} is neither measured, nor a cell or FitRequest field")
            row[column] = source[column]
        return row


@dataclass
class _Material:
    """What one (request, control) reads: the splits' low-dim rows, where their features stream from, and the
    encoder's name. Features are never held: each cell streams them (graftcache.fit.stream)."""

    train: LowDim
    eval: LowDim
    source: FeatureSource
    cache: FeatureCache
    encoder: str
    grid: tuple[int, int]
    targets: FeatureSource | None = None    # native tokens, for objectives that need them
    target_rows: np.ndarray | None = None   # the native cache's row of every train frame
    dropped: int = 0  # suite frames dropped for a NaN/inf state or action chunk (--drop-nonfinite)


class Fitter:
    """Runs every cell of a FitRequest; `run()` returns the rows it wrote."""

    def __init__(self, req: FitRequest, log: Callable[[str], None] = print,
                 backbones: BackbonePool | None = None, numerics: dict[str, NumericsCheck] | None = None) -> None:
        """`backbones` and `numerics` (cache key -> verdict) may be shared by the Fitters of one process (a
        sweep), so each policy is loaded and each cache's numerics probe recomputed once per process."""
        self.device = resolve_device(req.device)
        self.req = req = dataclasses.replace(req, compute_dtype=resolve_compute_dtype(req.compute_dtype, self.device),
                                             cells_per_pass=req.cells_per_pass
                                             or default_cells_per_pass(req.backbone, self.device))
        self.objective = OBJECTIVES[req.objective]
        self.log = log
        self.backbones = backbones or BackbonePool(log)
        self.root = reading_root(req.cache)  # only read: stage 2 never writes into a cache root
        self.dtype = resolve_dtype(req.compute_dtype)
        self.controls = [get_control(c) for c in dict.fromkeys(("none", *req.controls))]
        self.cache = find_cache(self.root, req.encoder, dataset=req.dataset, key=req.cache_key)
        needs_native = self.objective.needs_native or any(c.native_cache for c in self.controls)
        self.native_cache = (find_cache(self.root, native_name(req.backbone), dataset=req.dataset,
                                        key=req.native_cache_key, same_dataset_as=self.cache, for_what="native "
                                        "controls and the align objective") if needs_native else None)
        if self.native_cache is not None:
            strides = {c.manifest.frame_stride for c in (self.cache, self.native_cache)}
            if len(strides) > 1:
                raise FitError(f"caches {self.cache.key} and {self.native_cache.key} hold different frames (frame "
                               f"strides {sorted(strides)}); extract both with the same --frame-stride")
        for control in self.controls:  # a pool control far finer than the stored grid: refused before any load
            source = self._source(control)
            note = check_pool_grid(control, [parse_grid(g) for g in source.manifest.grids], f"cache {source.key}")
            if note:
                log(note)
        self.policy_folder = resolve_policy(req.backbone, req.policy, self.cache.manifest.dataset_identity,
                                            cache_root(req.cache), self.cache.manifest.dataset.source)
        self.cameras = self._match_cameras()
        self.index = suite_index_table(self.cache, req.suite)
        self.split = split_episodes(self.index, eval_fraction=req.eval_fraction, seed=req.eval_split_seed,
                                    rule=req.eval_split)
        self._materials: dict[tuple, _Material] = {}
        self._pass_keys: dict[str, tuple | None] = {}  # control name -> its pass key
        self._numerics = {} if numerics is None else numerics  # cache key -> verdict, before the first cell runs
        self._enforced: set[str] = set()  # verdicts this request has acted on (refused, warned)
        # reading in this process, the blocks cells read are kept for the next cells, up to another --buffer-mib
        self._memo = BlockMemo(req.buffer_mib * MIB) if req.num_workers == 0 else None
        self.reader = CacheReader()  # every source's: each block is checked once per fit, in whichever process

    def _match_cameras(self) -> dict[str, str]:
        """Policy camera -> the cache camera feeding it (graftcache/cameras.py: by name unless `camera_map` says
        otherwise), read from the policy's config and checked against every cache the fit reads."""
        policy = get_backbone(self.req.backbone).read_cameras(self.policy_folder)
        mapping: dict[str, str] = {}
        for cache in (self.cache, self.native_cache):
            if cache is not None:
                mapping = match_cameras(policy, cache.manifest.cameras, self.req.camera_map,
                                        policy_name=str(self.policy_folder), cache_name=f"cache {cache.key}")
        if renames(mapping):
            self.log(f"cameras mapped as asked (policy=cache): {format_camera_map(mapping)}")
        return mapping

    # ---------------------------------------------------------------- cells
    def _source(self, control: Control) -> FeatureCache:
        """The cache a control reads: the native tower's for the native controls, else the encoder's."""
        return self.native_cache if control.native_cache else self.cache

    def _objective(self, control: Control) -> Objective:
        return self.objective if control.train else EVAL_ONLY

    # ---------------------------------------------------------------- numerics
    def _check_numerics(self) -> None:
        """Recompute every cache's numerics probe here, once, before the first cell that runs (a finished grid
        loads nothing). Drift is refused unless `accept_numerics_drift`; an unchecked cache is a warning."""
        for cache in (self.cache, self.native_cache):
            if cache is None or cache.key in self._enforced:
                continue
            if cache.key not in self._numerics:
                self._numerics[cache.key] = check_numerics(cache, device=self.device)
            check = self._numerics[cache.key]
            self._enforced.add(cache.key)
            check.enforce("fit", accept=self.req.accept_numerics_drift, log=self.log,  # rows record the drift
                          unchecked="its rows record numerics_drift as null")

    def _drift(self, mat: _Material) -> float | None:
        """Largest numerics drift over the caches a cell reads; None when one of them could not be checked."""
        caches = [mat.cache, *([self.native_cache] if mat.targets is not None else [])]
        drifts = [self._numerics[c.key].drift for c in caches]
        return None if None in drifts else max(drifts)

    def cell(self, control: Control, seed: int, policy_id: str) -> Cell:
        """What identifies a results row (hashed into its run_id); computable without loading anything."""
        req, objective = self.req, self._objective(control)
        scheduled = objective.scheduled
        return Cell(
            backbone=req.backbone, policy=policy_id, cache_key=self._source(control).key, suite=req.suite, seed=seed,
            control=control.name, pool_grid=format_grid(control.grid or self.token_grid),
            objective=objective.name, steps=req.steps if scheduled else 0, lr=req.lr if scheduled else 0.0,
            batch_size=req.batch_size if scheduled else 0, buffer_mib=req.buffer_mib if scheduled else 0,
            lora_rank=req.lora_rank if control.lora else 0,
            eval_fraction=req.eval_fraction, eval_split_seed=req.eval_split_seed, eval_split=req.eval_split,
            eval_frames=req.eval_frames,
            num_denoise_steps=req.num_denoise_steps, compute_dtype=req.compute_dtype,
            camera_map=format_camera_map(self.cameras) if renames(self.cameras) else None,
        )

    @functools.cached_property
    def token_grid(self) -> tuple[int, int]:
        """The backbone's per-camera token grid, read from the policy's config (nothing is loaded)."""
        return get_backbone(self.req.backbone).read_token_grid(self.policy_folder)

    @property
    def policy_id(self) -> str:
        """How rows name the policy: as given, or `tiny:<folder>` for the tiny policy trained on this dataset."""
        return self.req.policy if self.req.policy != "tiny" else f"tiny:{Path(self.policy_folder).name}"

    def cells(self) -> list[tuple[Control, int, Cell]]:
        """Every (control, seed) of the request with its Cell, in the order `run` visits them."""
        return [(control, seed, self.cell(control, seed, self.policy_id))
                for seed in self.req.seeds for control in self.controls]

    def run(self) -> list[dict[str, Any]]:
        """Every missing cell, `cells_per_pass` cells to a pass of the backbone where they can share one
        (graftcache/fit/passes.py), each row appended to the results file as its pass finishes."""
        return run_passes([self])

    def skipped(self, cells: Sequence[tuple[Control, int]]) -> None:
        """Say in one line which of this request's cells are skipped, their rows being in the results file already:
        by control (with the tower a native control reads), the seeds of each."""
        seeds: dict[str, list[str]] = {}
        for control, seed in cells:
            source = self._source(control).manifest.encoder_name
            name = control.name if source == self.req.encoder else f"{control.name} ({source})"
            seeds.setdefault(name, []).append(str(seed))
        which = "; ".join(f"{name}: seed{'s' * (len(s) > 1)} {', '.join(s)}" for name, s in seeds.items())
        self.log(f"skip {self.req.backbone}/{self.req.encoder}/{self.req.suite}: {len(cells)} "
                 f"cell{'s' * (len(cells) > 1)} already in {self.req.results} (control {which})")

    def close(self) -> None:
        """Drop what this Fitter keeps for its next cells (blocks read, low-dim tables) once it has none left."""
        self._materials.clear()
        if self._memo is not None:
            self._memo = BlockMemo(self._memo.budget)

    def pass_key(self, control: Control) -> tuple | None:
        """What cells must share to train in one pass of the backbone (graftcache/fit/passes.py): the loaded
        policy and its compute dtype, the shape of the tokens fed to it (grid and width), the training schedule
        and the scoring's denoising, and the request's `cells_per_pass`. None: the cell runs alone (LoRA, align,
        controls that train nothing). Read from the policy's config and the cache's layout: nothing is loaded."""
        if control.name not in self._pass_keys:
            key = None
            adapter = get_backbone(self.req.backbone)
            if control.fuses and self._objective(control).fuses and adapter.per_sample_loss:
                req = self.req
                grid = control.grid or self.token_grid
                source = FeatureSource.of(self._source(control), list(self.cameras.values()), grid)
                width = source.frame_shape(source.cameras[0])[1]
                key = (req.backbone, str(self.policy_folder), str(self.device), req.compute_dtype, grid, width,
                       req.steps, req.batch_size, req.num_denoise_steps, req.cells_per_pass)
            self._pass_keys[control.name] = key
        return self._pass_keys[control.name]

    def run_pass(self, members: Sequence[Member]) -> list[dict[str, Any]]:
        """The rows of `members`, cells of this or other Fitters of one pass key (`plan_passes`), in order."""
        if len(members) == 1:
            (m,) = members
            return [m.fitter.run_cell(m.control, m.seed)]
        return self._run_fused(members)

    def run_cell(self, control: Control, seed: int) -> dict[str, Any]:
        """Fit and score one cell (any control, any seed: the others are not run) and return its row without
        writing it, so that a distributed sweep's driver stays the results file's only writer."""
        self._check_numerics()
        adapter = self.backbones.get(self.req.backbone, self.policy_folder, str(self.device))
        cell = self.cell(control, seed, self.policy_id)
        return self._told(self._run_cell(adapter, control, cell, self._material(adapter, control)), control)

    def _told(self, row: dict[str, Any], control: Control) -> dict[str, Any]:
        """`row`, once its scores are in the log."""
        shared = f" (its share of a pass of {row['cells_per_pass']})" if row["cells_per_pass"] > 1 else ""
        self.log(f"{row['backbone']}/{row['encoder']}/{row['suite']} seed {row['seed']} control {control.name} "
                 f"(cell {row['run_id']}): eval_mse {row['eval_mse']:.4f} (first {row['eval_mse_first']:.4f}, raw "
                 f"{row['eval_mse_raw']:.5f}) on {row['n_eval_frames']} frames "
                 f"({row['eval_seconds_per_frame'] * 1e3:.1f} ms a frame at --eval-batch-size "
                 f"{row['eval_batch_size']}), {row['wall_s']:.1f}s{shared}; activation checkpointing "
                 f"{row['activation_checkpointing']}")
        return row

    # ---------------------------------------------------------------- one cell
    def _material(self, adapter, control: Control) -> _Material:
        """The splits' low-dim rows a control reads, loaded once per (cache, array) and kept for the next cell."""
        grid = control.grid or adapter.token_grid
        source = self._source(control)
        key = (source.key, control.extra, None if control.extra else grid)
        if key not in self._materials:
            cams = list(self.cameras.values())
            low, dropped = drop_nonfinite(load_lowdim(source, self.req.suite, chunk=adapter.chunk_size), source,
                                          drop=self.req.drop_nonfinite)
            target_rows = None
            if self._objective(control).needs_native:  # features and targets: the same frames, by dataset index
                native = suite_index_table(self.native_cache, self.req.suite)
                at = pl.DataFrame({"index": low.index}).join(native.select("index", "row"), on="index", how="left",
                                                             maintain_order="left")["row"]
                low = low.take(np.flatnonzero(at.is_not_null().to_numpy()))
                target_rows = at.drop_nulls().to_numpy().astype(np.int64)
            train_at = np.flatnonzero(np.isin(low.episode_index, self.split.train_episodes))
            mat = _Material(low.take(train_at), low.subset(self.split.eval_episodes).evenly(self.req.eval_frames),
                            FeatureSource.of(source, cams, grid, control.extra, self.reader), source,
                            source.manifest.encoder_name, grid, dropped=dropped)
            if target_rows is not None:
                mat.targets = FeatureSource.of(self.native_cache, cams, None, "connector", self.reader)
                mat.target_rows = target_rows[train_at]
            self._materials[key] = mat
        return self._materials[key]

    def _feed(self, mat: _Material, low: LowDim, control: Control, seed: int) -> SplitFeed:
        """A split as a cell streams it, paired by the control (seeded per split as the cell's seed says)."""
        return SplitFeed(low, mat.source, int(mat.cache.layout["block_frames"]), control.pairing(len(low), seed),
                         drop=self.req.drop_nonfinite, memo=self._memo)

    def _run_cell(self, adapter, control: Control, cell: Cell, mat: _Material) -> dict[str, Any]:
        t0 = time.perf_counter()
        torch.manual_seed(cell.seed)
        width = mat.source.frame_shape(mat.source.cameras[0])[1]
        adapter.graft(control.projector(width, adapter.lm_width))
        if control.lora:
            adapter.add_lora(rank=self.req.lora_rank)
        self.backbones.describe(adapter, f"cell {cell.run_id} ({mat.encoder} seed {cell.seed} control {control.name})")
        cams = self.cameras
        adapter.set_activation_checkpointing(False)  # only a training step uses it (what the last cell left)
        if control.train and self._objective(control).scheduled:  # refused here, not OOM-killed later
            check_step_memory(adapter, mat.train, cams, mat.source, batch_size=self.req.batch_size,
                              buffer_mib=self.req.buffer_mib, dtype=self.dtype,
                              checkpointing=self.req.activation_checkpointing)
        checkpointing = "on" if adapter.activation_checkpointing else "off"
        stats = StreamStats()
        loss = self._objective(control).fit(Fitting(
            adapter=adapter, req=self.req, control=control, train=self._feed(mat, mat.train, control, cell.seed),
            cams=cams, targets=(mat.targets, mat.target_rows) if mat.targets is not None else None, grid=mat.grid,
            seed=cell.seed, dtype=self.dtype, stats=stats))
        t_eval = time.perf_counter()
        with closing(read_blocks(self._feed(mat, mat.eval, control, cell.seed + 1).features(seed=None),
                                 self.req.num_workers, stats)) as blocks:
            score = evaluate(adapter, mat.eval, blocks, cams, batch_size=self.req.eval_batch_size,
                             transform=control.transform, dtype=self.dtype,
                             num_denoise_steps=self.req.num_denoise_steps)
        eval_s = time.perf_counter() - t_eval
        wall = time.perf_counter() - t0
        if control.train:
            self._save_projector(adapter, cell)
        return self._row(adapter, cell, mat, loss, score, stats, wall, cells=1, checkpointing=checkpointing,
                         eval_s=eval_s)

    def _run_fused(self, members: Sequence[Member]) -> list[dict[str, Any]]:
        """Train and score several cells (of this and other Fitters of this pass key) in one pass of the backbone:
        their projectors grafted together (graftcache.graft.FusedProjector), each initialised, fed, optimised and
        scored as it would be alone (graftcache.fit.loop.optimise_together, evaluate_together)."""
        t0 = time.perf_counter()
        for m in members:
            m.fitter._check_numerics()
        adapter = self.backbones.get(self.req.backbone, self.policy_folder, str(self.device))
        mats = [m.fitter._material(adapter, m.control) for m in members]
        projectors = []
        for m, mat in zip(members, mats, strict=True):
            torch.manual_seed(m.cell.seed)  # each projector starts where it starts alone
            projectors.append(m.control.projector(mat.source.frame_shape(mat.source.cameras[0])[1], adapter.lm_width))
        fused = FusedProjector(projectors)
        adapter.graft(fused)
        self.backbones.describe(adapter, f"the {len(members)} cells of a backbone pass, each training its own "
                                f"projector ({', '.join(m.cell.run_id for m in members)})")
        check_step_memory(adapter, mats[0].train, self.cameras, mats[0].source, batch_size=self.req.batch_size,
                          buffer_mib=self.req.buffer_mib, dtype=self.dtype,
                          checkpointing=self.req.activation_checkpointing,
                          others=[(mat.train, mat.source, m.fitter.req.buffer_mib)
                                  for m, mat in zip(members[1:], mats[1:], strict=True)],
                          route=lambda sizes: fused.rows([*sizes, *[0] * (len(members) - len(sizes))]))
        checkpointing = "on" if adapter.activation_checkpointing else "off"
        stats = [StreamStats() for _ in members]
        with ExitStack() as stack:
            learners = []
            for m, mat, projector, st in zip(members, mats, projectors, stats, strict=True):
                f = m.fitter
                buffer = stack.enter_context(flow_buffer(f._feed(mat, mat.train, m.control, m.seed), f.req, m.seed, st))
                learners.append(learner(mat.train, buffer, f.cameras, list(projector.parameters()),
                                        batch_size=f.req.batch_size, lr=f.req.lr, seed=m.seed,
                                        transform=m.control.transform))
            optimise_together(adapter, learners, steps=self.req.steps, batch_size=self.req.batch_size,
                              dtype=self.dtype, route=fused.rows, show=self.req.progress, leave=False)
        t_eval = time.perf_counter()
        with ExitStack() as stack:
            scores = evaluate_together(adapter, [
                Scoring(mat.eval, stack.enter_context(closing(read_blocks(
                    m.fitter._feed(mat, mat.eval, m.control, m.seed + 1).features(seed=None), m.fitter.req.num_workers,
                    st))), m.fitter.cameras, m.control.transform)
                for m, mat, st in zip(members, mats, stats, strict=True)],
                batch_size=self.req.eval_batch_size, dtype=self.dtype, num_denoise_steps=self.req.num_denoise_steps,
                route=fused.rows)
        eval_share = (time.perf_counter() - t_eval) / len(members)
        prefix = next(name for name, module in adapter.policy.named_modules() if module is fused)
        share = (time.perf_counter() - t0) / len(members)
        rows = []
        for m, mat, projector, one, score, st in zip(members, mats, projectors, learners, scores, stats, strict=True):
            m.fitter._save_projector(adapter, m.cell, {f"{prefix}.{n}": p for n, p in projector.named_parameters()})
            rows.append(m.fitter._told(m.fitter._row(adapter, m.cell, mat, one.final_loss, score, st, share,
                                                     cells=len(members), checkpointing=checkpointing,
                                                     eval_s=eval_share), m.control))
        return rows

    def _row(self, adapter, cell: Cell, mat: _Material, loss: float, score, stats: StreamStats, wall: float, *,
             cells: int, checkpointing: str, eval_s: float) -> dict[str, Any]:
        """A cell's row from what it measured (`cells`: how many cells its backbone pass trained; `checkpointing`:
        on or off as the step ran; `eval_s`: its scoring's seconds, its share of a pass's)."""
        if isinstance(self.root, ReadThroughRoot):  # what the reading processes copied locally for this cell
            self.root.fetched_bytes += stats.fetched
        return cell.row(self.req, {
            "run_id": cell.run_id, "format_version": results.FORMAT_VERSION, "policy_sha256": adapter.policy_sha256,
            "encoder": mat.encoder,
            "pool_grid": format_grid(mat.grid), "train_loss_final": loss, "eval_mse": score.mse,
            "eval_mse_first": score.mse_first, "eval_mse_raw": score.mse_raw, "eval_mse_arm": score.mse_arm,
            "eval_mse_gripper": score.mse_gripper,
            "eval_mse_episodes": [score.per_episode[e] for e in sorted(score.per_episode)],
            "eval_ci_mse": score.ci_mse,
            "eval_ci_mse_episodes": [score.ci_per_episode[e] for e in sorted(score.per_episode)],
            "backbone_params": adapter.n_params,
            "n_eval_frames": score.n_frames, "n_eval_episodes": len(score.per_episode), "wall_s": wall,
            "cells_per_pass": cells, "device": str(self.device),
            "random_init": bool(mat.cache.manifest.random_init or adapter.random_init),
            "encoder_random_init": bool(mat.cache.manifest.random_init),
            "backbone_random_init": bool(adapter.random_init),
            "n_dropped_nonfinite": mat.dropped + len(stats.dropped), "numerics_drift": self._drift(mat),
            "camera_map": format_camera_map(self.cameras), "graftcache_version": graftcache.__version__,
            "activation_checkpointing": checkpointing, "eval_seconds_per_frame": eval_s / score.n_frames,
        })

    def run_folder(self, cell: Cell) -> Path:
        """Where a cell's projector (and a row its results file could not take) is kept."""
        return self.runs / cell.run_id

    @functools.cached_property
    def runs(self) -> Path:
        """The folder of the run folders: --out, else runs/ beside the results file; where that cannot be written
        (a read-only results folder), runs/ in the local cache folder (store.cache_root), said in the log: the
        projector save would fail first and lose the cell's work, its row then being kept there too."""
        if self.req.out:
            return Path(self.req.out)
        beside = Path(self.req.results).absolute().parent / "runs"
        existing = next(p for p in (beside, *beside.parents) if p.exists())  # what creating it writes into
        if os.access(existing, os.W_OK | os.X_OK):  # False on a read-only mount, also for root
            return beside
        runs = cache_root(self.req.cache) / "runs"
        self.log(f"cannot write run folders beside {self.req.results} ({existing} is not writable): projectors, and "
                 f"rows the results file cannot take, are kept in {runs} (--out names another folder)")
        return runs

    def _save_projector(self, adapter, cell: Cell, trainable: Mapping[str, torch.Tensor] | None = None) -> None:
        """The cell's trained parameters (default: every trainable one of the policy), named as in the policy."""
        folder = self.run_folder(cell)
        folder.mkdir(parents=True, exist_ok=True)
        if trainable is None:
            trainable = {n: p for n, p in adapter.policy.named_parameters() if p.requires_grad}
        save_file({n: p.detach().cpu().contiguous() for n, p in trainable.items()},
                  str(folder / "projector.safetensors"))
        follow_umask(folder / "projector.safetensors")
        sidecar = {"run_id": cell.run_id, "cell": asdict(cell), "split": asdict(self.split),
                   "freeze": str(adapter.freeze_report()), "graftcache_version": graftcache.__version__}
        (folder / "projector.json").write_text(json.dumps(sidecar, indent=2, default=str))
