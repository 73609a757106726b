"""One fit, top to bottom: caches -> cells (seed x control) -> one results row per cell.

A cell is fitted against the frozen policy, loaded once per run and reset to its pristine state
between cells (graft surgery mutates it), from cached features only. Finished cells (same run_id in
the results file) are skipped before anything is loaded, so reruns and sweeps resume where they
stopped and a finished grid only reads. The projector of every trained cell is saved as safetensors
with a JSON sidecar in the run folder.

The parts a cell is made of are registries: its control (fit/controls.py: which cache, which projector,
which feature transform) and its objective (fit/objectives.py: how the projector is fitted).
"""

from __future__ import annotations

import dataclasses
import json
import time
from collections.abc import Callable, Mapping
from contextlib import closing
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
from graftcache.file_lease import FileLease
from graftcache.fit.buffer import MIB
from graftcache.fit.controls import Control, get_control
from graftcache.fit.data import LowDim, drop_nonfinite, load_lowdim, split_episodes, suite_index_table
from graftcache.fit.feed import SplitFeed
from graftcache.fit.lookup import find_cache
from graftcache.fit.loop import evaluate
from graftcache.fit.objectives import EVAL_ONLY, OBJECTIVES, Fitting, Objective
from graftcache.fit.step_memory import check_step_memory
from graftcache.fit.stream import BlockMemo, FeatureSource, StreamStats, read_chunks
from graftcache.pooling import format_grid
from graftcache.requests import FitRequest
from graftcache.runtime import resolve_compute_dtype, resolve_device, resolve_dtype, set_main_threads
from graftcache.store import FeatureCache, cache_root
from graftcache.store.readthrough import ReadThroughRoot, reading_root

__all__ = ["Cell", "FitRequest", "Fitter"]


@dataclass(frozen=True)
class Cell:
    """What identifies one results row. Its fields, by name and value, are the bytes of the row's
    run_id: renaming or retyping one would make finished rows unrecognisable, so never do.

    `camera_map` is the one field left out of the run_id when it is None: a cell whose policy cameras are each
    fed by the cache camera of the same name (the policy and the cache, both in the cell, already decide that),
    so such rows keep the run_ids they had before cameras could be mapped. A mapping that renames changes which
    frames feed a slot, so it is hashed: two mappings of one cache never share a row."""

    backbone: str
    policy: str
    cache_key: str
    suite: str
    seed: int
    control: str
    pool_grid: str            # "native" or the control's HxW
    objective: str            # "flow" | "align" | "eval"
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

    @property
    def run_id(self) -> str:
        cell = asdict(self)
        if cell["camera_map"] is None:
            del cell["camera_map"]
        return results.make_run_id(cell)

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
    encoder identity. Features are never held: each cell streams them (graftcache.fit.stream)."""

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
        self.req = req = dataclasses.replace(req, compute_dtype=resolve_compute_dtype(req.compute_dtype, self.device))
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
            strides = {c.manifest.get("frame_stride") or 1 for c in (self.cache, self.native_cache)}
            if len(strides) > 1:
                raise FitError(f"caches {self.cache.key} and {self.native_cache.key} hold different frames (frame "
                               f"strides {sorted(strides)}); extract both with the same --frame-stride")
        self.policy_folder = resolve_policy(req.backbone, req.policy, self.cache.manifest["dataset_fingerprint"],
                                            cache_root(req.cache), self.cache.manifest["dataset"]["source"])
        self.cameras = self._match_cameras()
        self.index = suite_index_table(self.cache, req.suite)
        self.split = split_episodes(self.index, eval_fraction=req.eval_fraction, seed=req.eval_split_seed)
        self._materials: dict[tuple, _Material] = {}
        self._numerics = {} if numerics is None else numerics  # cache key -> verdict, before the first cell runs
        self._enforced: set[str] = set()  # verdicts this request has acted on (refused, warned)
        # reading in this process, the blocks cells read are kept for the next cells, up to another --buffer-mib
        self._memo = BlockMemo(req.buffer_mib * MIB) if req.num_workers == 0 else None

    def _match_cameras(self) -> dict[str, str]:
        """Policy camera -> the cache camera feeding it (graftcache/cameras.py: by name unless `camera_map` says
        otherwise), read from the policy's config and checked against every cache the fit reads."""
        policy = get_backbone(self.req.backbone).read_cameras(self.policy_folder)
        mapping: dict[str, str] = {}
        for cache in (self.cache, self.native_cache):
            if cache is not None:
                mapping = match_cameras(policy, cache.manifest["cameras"], self.req.camera_map,
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
            control=control.name, pool_grid=format_grid(control.grid) if control.grid else "native",
            objective=objective.name, steps=req.steps if scheduled else 0, lr=req.lr if scheduled else 0.0,
            batch_size=req.batch_size if scheduled else 0, buffer_mib=req.buffer_mib if scheduled else 0,
            lora_rank=req.lora_rank if control.lora else 0,
            eval_fraction=req.eval_fraction, eval_split_seed=req.eval_split_seed, eval_frames=req.eval_frames,
            num_denoise_steps=req.num_denoise_steps, compute_dtype=req.compute_dtype,
            camera_map=format_camera_map(self.cameras) if renames(self.cameras) else None,
        )

    @property
    def policy_id(self) -> str:
        """How rows name the policy: as given, or `tiny:<folder>` for the tiny policy trained on this dataset."""
        return self.req.policy if self.req.policy != "tiny" else f"tiny:{Path(self.policy_folder).name}"

    def cells(self) -> list[tuple[Control, int, Cell]]:
        """Every (control, seed) of the request with its identity, in the order `run` visits them."""
        return [(control, seed, self.cell(control, seed, self.policy_id))
                for seed in self.req.seeds for control in self.controls]

    def run(self) -> list[dict[str, Any]]:
        """Every missing cell, one after the other, each row appended to the results file as it finishes.

        Other processes (fits, sweeps, here or on other machines) may write the same results file: a cell is
        computed only under its claim (results.cell_claim), so a cell another process is computing is left
        for later, then skipped once its row is in the file (or computed here if that process died)."""
        set_main_threads()
        done = results.done_run_ids(self.req.results)
        rows = []
        pending = [(control, seed, cell) for control, seed, cell in self.cells() if not self._skip(control, cell, done)]
        claims = {cell.run_id: results.cell_claim(self.req.results, cell.run_id) for _, _, cell in pending}
        told: set[str] = set()
        while pending:
            busy = []
            for control, seed, cell in pending:
                claim = claims[cell.run_id]
                if not self._claim(claim):
                    if cell.run_id not in told:
                        self.log(f"cell {cell.run_id} (seed {seed} control {control.name}) is being computed by "
                                 f"{claim.holder()}: waiting for its row")
                        told.add(cell.run_id)
                    busy.append((control, seed, cell))
                    continue
                try:
                    if not self._skip(control, cell, results.done_run_ids(self.req.results)):
                        row = self.run_cell(control, seed)
                        results.append_or_keep(self.req.results, row, self.run_folder(cell))
                        rows.append(row)
                finally:
                    claim.release()
            if busy:
                time.sleep(1.0)
            pending = busy
        return rows

    def _skip(self, control: Control, cell: Cell, done: set[str]) -> bool:
        """Whether the cell's row is in the results file already (said so in the log)."""
        if cell.run_id not in done:
            return False
        encoder = self._source(control).manifest["encoder"]
        self.log(f"skip {self.req.backbone}/{encoder['name']}/{self.req.suite} seed {cell.seed} "
                 f"control {control.name}: already in {self.req.results}")
        return True

    def _claim(self, claim: FileLease) -> bool:
        """Take a cell's claim; where no claim can be made (a read-only place) the cell runs unclaimed, and its
        row is then kept by results.append_or_keep."""
        try:
            return claim.try_acquire()
        except OSError:
            return True

    def run_cell(self, control: Control, seed: int) -> dict[str, Any]:
        """Fit and score one cell (any control, any seed: the others are not run) and return its row without
        writing it, so that a distributed sweep's driver stays the results file's only writer."""
        self._check_numerics()
        adapter = self.backbones.get(self.req.backbone, self.policy_folder, str(self.device))
        cell = self.cell(control, seed, self.policy_id)
        row = self._run_cell(adapter, control, cell, self._material(adapter, control))
        self.log(f"{row['backbone']}/{row['encoder']}/{row['suite']} seed {seed} control {control.name}: "
                 f"eval_mse {row['eval_mse']:.4f} (first {row['eval_mse_first']:.4f}, raw "
                 f"{row['eval_mse_raw']:.5f}) on {row['n_eval_frames']} frames, {row['wall_s']:.1f}s")
        return row

    # ---------------------------------------------------------------- one cell
    def _material(self, adapter, control: Control) -> _Material:
        """The splits' low-dim rows a control reads, loaded once per (cache, array) and kept for the next cell."""
        grid = control.grid or adapter.native_grid
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
                            FeatureSource.of(source, cams, grid, control.extra), source,
                            source.manifest["encoder"]["name"], grid, dropped=dropped)
            if target_rows is not None:
                mat.targets = FeatureSource.of(self.native_cache, cams, None, "connector")
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
        params = adapter.n_params  # the policy as loaded: read before the graft replaces its tower
        width = mat.source.frame_shape(mat.source.cameras[0])[1]
        adapter.graft(control.projector(width, adapter.lm_width))
        if control.lora:
            adapter.add_lora(rank=self.req.lora_rank)
        self.log(f"cell {cell.run_id}: {adapter.freeze_report()}")
        cams = self.cameras
        if control.train and self._objective(control).scheduled:  # refused here, not OOM-killed later
            check_step_memory(adapter, mat.train, cams, mat.source, batch_size=self.req.batch_size,
                              buffer_mib=self.req.buffer_mib, dtype=self.dtype)
        stats = StreamStats()
        loss = self._objective(control).fit(Fitting(
            adapter=adapter, req=self.req, control=control, train=self._feed(mat, mat.train, control, cell.seed),
            cams=cams, targets=(mat.targets, mat.target_rows) if mat.targets is not None else None, grid=mat.grid,
            seed=cell.seed, dtype=self.dtype, stats=stats))
        with closing(read_chunks(self._feed(mat, mat.eval, control, cell.seed + 1).features(seed=None),
                                 self.req.num_workers, stats)) as chunks:
            score = evaluate(adapter, mat.eval, chunks, cams, transform=control.transform, dtype=self.dtype,
                             num_denoise_steps=self.req.num_denoise_steps)
        if isinstance(self.root, ReadThroughRoot):  # what the reading processes copied locally for this fit
            self.root.fetched_bytes += stats.fetched
        wall = time.perf_counter() - t0
        if control.train:
            self._save_projector(adapter, cell)
        return cell.row(self.req, {
            "run_id": cell.run_id, "policy_sha256": adapter.policy_sha256, "encoder": mat.encoder,
            "pool_grid": format_grid(mat.grid), "train_loss_final": loss, "eval_mse": score.mse,
            "eval_mse_first": score.mse_first, "eval_mse_raw": score.mse_raw,
            "eval_mse_episodes": [score.per_episode[e] for e in sorted(score.per_episode)],
            "eval_ci_mse": score.ci_mse,
            "eval_ci_mse_episodes": [score.ci_per_episode[e] for e in sorted(score.per_episode)],
            "backbone_params": params,
            "n_eval_frames": score.n_frames, "n_eval_episodes": len(score.per_episode), "wall_s": wall,
            "device": str(self.device),
            "random_init": bool(mat.cache.manifest.get("random_init") or adapter.random_init),
            "n_dropped_nonfinite": mat.dropped + len(stats.dropped), "numerics_drift": self._drift(mat),
            "camera_map": format_camera_map(self.cameras), "graftcache_version": graftcache.__version__,
        })

    def run_folder(self, cell: Cell) -> Path:
        """Where a cell's projector (and a row its results file could not take) is kept."""
        return (Path(self.req.out) if self.req.out else Path(self.req.results).parent / "runs") / cell.run_id

    def _save_projector(self, adapter, cell: Cell) -> None:
        folder = self.run_folder(cell)
        folder.mkdir(parents=True, exist_ok=True)
        trainable = {n: p.detach().cpu().contiguous() for n, p in adapter.policy.named_parameters() if p.requires_grad}
        save_file(trainable, str(folder / "projector.safetensors"))
        follow_umask(folder / "projector.safetensors")
        sidecar = {"run_id": cell.run_id, "cell": asdict(cell), "split": asdict(self.split),
                   "freeze": str(adapter.freeze_report()), "graftcache_version": graftcache.__version__}
        (folder / "projector.json").write_text(json.dumps(sidecar, indent=2, default=str))
