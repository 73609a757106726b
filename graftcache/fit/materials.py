"""What the cells of one Plan read: the loaded backbone, the caches' numerics verdicts, and per control
the splits' low-dim rows and the feature streams (`Reading`), kept for the request's next cells.

A `Materials` belongs to one process (a fit, a sweep's local executor, a Ray worker): the backbones (a LoadedBackbones)
and the numerics verdicts may be shared by every request that process runs, so each policy is loaded and each cache's
numerics probe recomputed once per process. Features are never held: each cell streams them (graftcache.fit.stream).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import polars as pl

from graftcache.backbones.base import BackboneAdapter
from graftcache.backbones.loaded import LoadedBackbones
from graftcache.encoders.fingerprint import NumericsCheck, check_numerics
from graftcache.fit.buffer import MIB
from graftcache.fit.controls import Control
from graftcache.fit.data import LowDim, drop_nonfinite, load_lowdim, suite_index_table
from graftcache.fit.dose import Dose, Seen, measure_spread
from graftcache.fit.feed import SplitFeed
from graftcache.fit.plan import Plan
from graftcache.fit.stream import BlockMemo, CacheReader, FeatureSource
from graftcache.runtime import resolve_dtype
from graftcache.store import FeatureCache

__all__ = ["Materials", "Reading"]


@dataclass
class Reading:
    """What one (request, control) reads: the splits' low-dim rows, where their features stream from, and the
    encoder's name."""

    train: LowDim
    eval: LowDim
    source: FeatureSource
    cache: FeatureCache
    encoder: str
    grid: tuple[int, int]                   # what the features are pooled to (graftcache.fit.plan.Plan.grid)
    targets: FeatureSource | None = None    # native tokens, for objectives that need them
    target_rows: np.ndarray | None = None   # the native cache's row of every train frame
    dropped: int = 0  # suite frames dropped for a NaN/inf state or action chunk (--drop-nonfinite)


class Materials:
    """The loaded things a Plan's cells read, loaded on first use and kept for its next cells."""

    def __init__(self, plan: Plan, backbones: LoadedBackbones | None = None,
                 numerics: dict[str, NumericsCheck] | None = None) -> None:
        self.plan = plan
        self.backbones = backbones or LoadedBackbones(plan.log)
        self.dtype = resolve_dtype(plan.req.compute_dtype)
        self._numerics = {} if numerics is None else numerics  # cache key -> verdict, before the first cell runs
        self._enforced: set[str] = set()  # verdicts this request has acted on (refused, warned)
        self._readings: dict[tuple, Reading] = {}
        self._spreads: dict[tuple, dict] = {}  # (cache, grid) -> the dose family's feature spread per camera
        # reading in this process, the blocks cells read are kept for the next cells, up to another --buffer-mib
        req = plan.req
        self._memo = BlockMemo(req.buffer_mib * MIB) if req.num_workers == 0 else None
        self.reader = CacheReader()  # every source's: each block is checked once per fit, in whichever process

    def check_numerics(self) -> None:
        """Recompute every cache's numerics probe here, once, before the first cell that runs (a finished sweep
        loads nothing). Drift is refused unless `accept_numerics_drift`; an unchecked cache is a warning."""
        plan = self.plan
        for cache in (plan.cache, plan.native_cache):
            if cache is None or cache.key in self._enforced:
                continue
            if cache.key not in self._numerics:
                self._numerics[cache.key] = check_numerics(cache, device=plan.device)
            check = self._numerics[cache.key]
            self._enforced.add(cache.key)
            check.enforce("fit", accept=plan.req.accept_numerics_drift, log=plan.log,  # rows record the drift
                          unchecked="its rows record numerics_drift as null")

    def drift(self, reading: Reading) -> float | None:
        """Largest numerics drift over the caches a cell reads; None when one of them could not be checked."""
        caches = [reading.cache, *([self.plan.native_cache] if reading.targets is not None else [])]
        drifts = [self._numerics[c.key].drift for c in caches]
        return None if None in drifts else max(drifts)

    def backbone(self) -> BackboneAdapter:
        """The request's policy, loaded once per process (reset between cells), its token grid checked against the
        one the plan read from its config."""
        plan = self.plan
        adapter = self.backbones.get(plan.req.backbone, plan.policy_folder, str(plan.device))
        plan.check_token_grid(adapter.token_grid)
        return adapter

    def reading(self, adapter: BackboneAdapter, control: Control) -> Reading:
        """The splits' low-dim rows a control reads, loaded once per (cache, array) and kept for the next cell."""
        plan, req = self.plan, self.plan.req
        grid = plan.grid(control)
        source = plan.source(control)
        key = (source.key, control.extra, None if control.extra else grid)
        if key not in self._readings:
            cams = list(plan.cameras.values())
            low, dropped = drop_nonfinite(load_lowdim(source, req.suite, chunk=adapter.chunk_size), source,
                                          drop=req.drop_nonfinite)
            target_rows = None
            if plan.objective_of(control).needs_native:  # features and targets: the same frames, by dataset index
                native = suite_index_table(plan.native_cache, req.suite)
                at = pl.DataFrame({"index": low.index}).join(native.select("index", "row"), on="index", how="left",
                                                             maintain_order="left")["row"]
                low = low.take(np.flatnonzero(at.is_not_null().to_numpy()))
                target_rows = at.drop_nulls().to_numpy().astype(np.int64)
            train_at = np.flatnonzero(np.isin(low.episode_index, plan.split.train_episodes))
            reading = Reading(low.take(train_at), low.subset(plan.split.eval_episodes).evenly(req.eval_frames),
                              FeatureSource.of(source, cams, grid, control.extra, self.reader), source,
                              source.manifest.encoder_name, grid, dropped=dropped)
            if target_rows is not None:
                reading.targets = FeatureSource.of(plan.native_cache, cams, None, "connector", self.reader)
                reading.target_rows = target_rows[train_at]
            self._readings[key] = reading
        return self._readings[key]

    def feed(self, reading: Reading, low: LowDim, control: Control, seed: int) -> SplitFeed:
        """A split as a cell streams it, paired by the control (seeded per split as the cell's seed says)."""
        return SplitFeed(low, reading.source, int(reading.cache.layout["block_frames"]),
                         control.pairing(len(low), seed), drop=self.plan.req.drop_nonfinite, memo=self._memo)

    def seen(self, reading: Reading, control: Control, seed: int) -> Seen:
        """What a cell of `control` and `seed` sees of a batch: its control's transform, and its dose where it has one
        (the spread measured once per cache and grid on the training split, kept for the next cells)."""
        if control.dose is None:
            return Seen(control.transform)
        key = (reading.source.key, reading.grid)
        if key not in self._spreads:
            self._spreads[key] = measure_spread(reading.source, reading.train)
        return Seen(control.transform, Dose(control.dose, self._spreads[key], seed))

    def close(self) -> None:
        """Drop what is kept for the next cells (blocks read, low-dim tables) once the request has none left."""
        self._readings.clear()
        if self._memo is not None:
            self._memo = BlockMemo(self._memo.budget)


#: How a runner finds a Plan's materials (one per Plan in a process).
MaterialsOf = Callable[[Plan], Materials]
