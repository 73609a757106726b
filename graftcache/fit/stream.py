"""Features streamed out of a cache in blocks, read by prefetching worker processes.

A fit never holds a split's features: at LIBERO scale (pi0.5's 16x16 grid, 768 wide, fp16, two cameras:
~0.8 MB a frame) a suite is 40-80 GB. Workers read blocks, pool them to the cell's grid
(graftcache.fit.data.read_grid), check them for NaN/inf and hand them over; the consumer keeps what it needs
(a bounded shuffle buffer for training, predictions for scoring, sufficient statistics for `align`).

The unit is a `Block`: the wanted frames of one cache block (`rows_by_block`). A block is one block file per array,
the unit a block checksum covers (stage 2 reads a block whole the first time it checks it) and the unit a remote root
copies locally (graftcache.store.readthrough), so a block costs one read of its file; benchmarks/bench_stream.py
measures what smaller runs inside a block would save.

Determinism: the block order is a pure function of (seed, epoch), block k is read by worker k mod W, and torch's
DataLoader takes items from IterableDataset workers round-robin, so the consumer sees block 0, 1, 2, ... for
any W and any timing. A GraftcacheError raised in a worker comes back as data (`Failure`) and is raised again
in the consumer with its own type and one-line message (torch would wrap it in a traceback).
"""

from __future__ import annotations

import itertools
import multiprocessing
import multiprocessing.context
import os
from collections import OrderedDict
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field

import numpy as np
import torch
from torch.utils.data import DataLoader, IterableDataset, get_worker_info

from graftcache.errors import FitError, GraftcacheError
from graftcache.fit.data import LowDim, nonfinite_message, read_grid
from graftcache.nonfinite import nonfinite_rows
from graftcache.runtime import single_thread_worker
from graftcache.store import FeatureCache
from graftcache.store.cache import STORAGE_DTYPES, BlockChecks
from graftcache.store.readthrough import reading_root
from graftcache.store.roots import is_url

PREFETCH_BLOCKS = 2  # blocks each worker reads ahead: with the consumer's one, what the stream holds beyond its buffer
Features = dict[str, torch.Tensor]  # camera -> [n, T, C] in stored precision


class CacheReader:
    """What one fit's processes share about the caches they read: the blocks already checked (`checks`, every
    handle's) and, per process, the handles opened.

    Handed to the worker processes with the stream they read: pickled (a fork server's or spawned workers), it
    keeps the checked blocks and drops the handles, whose store clients do not survive a process boundary; a
    forked worker inherits both and opens its own handles too. Either way each worker opens a cache once and
    checks only blocks no process of the fit has checked (the consumer adds what workers checked, `read_blocks`)."""

    def __init__(self) -> None:
        self.checks = BlockChecks()
        self._open: dict[tuple[str, str], FeatureCache] = {}
        self._pid = os.getpid()

    def __getstate__(self) -> dict:
        return {"checks": self.checks}

    def __setstate__(self, state: dict) -> None:
        self.checks, self._open, self._pid = state["checks"], {}, os.getpid()

    def adopt(self, cache: FeatureCache) -> None:
        """Read `cache` through the handle this process already has (its checks become the reader's)."""
        cache.checks = self.checks
        self._handles()[(cache.root.url, cache.key)] = cache

    def open(self, root: str, key: str) -> FeatureCache:
        """This process's handle on cache `key` of `root`, opened on first use."""
        handles = self._handles()
        if (root, key) not in handles:
            handles[(root, key)] = FeatureCache.in_root(reading_root(root), key, writable=False, checks=self.checks)
        return handles[(root, key)]

    def _handles(self) -> dict[tuple[str, str], FeatureCache]:
        if self._pid != os.getpid():  # a forked worker: its parent's handles are not its own
            self._open, self._pid = {}, os.getpid()
        return self._open


@dataclass(frozen=True)
class FeatureSource:
    """One array of some cameras of a cache, named by location so that each worker opens it itself (a remote
    root through its own local copies): a grid (pooled from a stored grid by read_grid) or a stored extra."""

    root: str
    key: str
    cameras: tuple[str, ...]
    grid: tuple[int, int] | None = None
    extra: str | None = None  # e.g. "connector": the native tower's post-connector tokens
    reader: CacheReader = field(default_factory=CacheReader, compare=False, repr=False)

    @classmethod
    def of(cls, cache: FeatureCache, cameras: Sequence[str], grid: tuple[int, int] | None,
           extra: str | None = None, reader: CacheReader | None = None) -> FeatureSource:
        """`reader`: the fit's (shared by its sources, so each block is checked once per fit), default a new one."""
        missing = [c for c in cameras if c not in cache.manifest.cameras]
        if missing:
            raise FitError(f"cache {cache.key} has no camera {missing}; it has {cache.manifest.cameras}")
        reader = reader or CacheReader()
        reader.adopt(cache)  # this process reads through its own handle
        return cls(cache.root.url, cache.key, tuple(cameras), None if extra else grid, extra, reader)

    def open(self) -> FeatureCache:
        """This process's handle on the cache (see CacheReader)."""
        return self.reader.open(self.root, self.key)

    def read(self, rows: np.ndarray) -> Features:
        return {c: self.read_camera(c, rows) for c in self.cameras}

    def read_camera(self, camera: str, rows: np.ndarray) -> torch.Tensor:
        cache = self.open()
        if self.extra is not None:
            return cache.read_features(camera, self.extra, rows)
        return read_grid(cache, camera, self.grid, rows)

    def frame_shape(self, camera: str) -> tuple[int, int]:
        """(tokens, width) of one frame of `camera` as read (after pooling)."""
        cache = self.open()
        if self.extra is not None:
            tokens, width = cache.layout["arrays"][cache.feature_path(camera, self.extra)]
            return int(tokens), int(width)
        stored = next(cache.feature_path(camera, g) for g in cache.manifest.grids)
        return self.grid[0] * self.grid[1], int(cache.layout["arrays"][stored][-1])

    def frame_bytes(self, cameras: Sequence[str] | None = None) -> int:
        """Bytes of one frame as read (after pooling, in stored precision) of `cameras`, default every camera."""
        itemsize = STORAGE_DTYPES[self.open().manifest.storage_dtype].itemsize
        return sum(int(np.prod(self.frame_shape(c))) for c in (self.cameras if cameras is None else cameras)) * itemsize


class BlockMemo:
    """Whole blocks this process has read, as a source reads them (pooled), kept for the cells after the one that
    read them, up to `budget` bytes (the least recently used go first).

    The cells of one (backbone, encoder, suite) read the same blocks again and again: every control and seed,
    for training and for scoring. On a small cache that is a large share of a cell (the demo's 8x8x1280 unpooled
    grids: docs/measured.md). Only reading in this process can keep them:
    workers are new processes for each stream, so a memo never travels to one (BlockStream drops it when
    pickled).
    """

    def __init__(self, budget: int) -> None:
        self.budget, self.nbytes = budget, 0
        self._blocks: OrderedDict[tuple[FeatureSource, str, int], torch.Tensor] = OrderedDict()

    def read(self, source: FeatureSource, rows: np.ndarray) -> Features:
        """`source.read(rows)`, the same values, from kept blocks where it can."""
        block_frames = int(source.open().layout["block_frames"])
        out: Features = {}
        for camera in source.cameras:
            if not len(rows) or block_frames * source.frame_bytes([camera]) > self.budget:
                out[camera] = source.read_camera(camera, rows)  # nothing to keep, or a block it could never keep
                continue
            blocks = rows // block_frames
            for b in np.unique(blocks):
                at = np.flatnonzero(blocks == b)
                whole = self._block(source, camera, int(b))
                if camera not in out:
                    out[camera] = torch.empty((len(rows), *whole.shape[1:]), dtype=whole.dtype)
                out[camera][torch.from_numpy(at)] = whole[torch.from_numpy(rows[at] - int(b) * block_frames)]
        return out

    def _block(self, source: FeatureSource, camera: str, block: int) -> torch.Tensor:
        key = (source, camera, block)
        if key in self._blocks:
            self._blocks.move_to_end(key)
            return self._blocks[key]
        lo, hi = source.open().block_range(block)
        values = source.read_camera(camera, np.arange(lo, hi))
        self._blocks[key] = values
        self.nbytes += values.numel() * values.element_size()
        while self.nbytes > self.budget:
            _, old = self._blocks.popitem(last=False)
            self.nbytes -= old.numel() * old.element_size()
        return values


@dataclass(frozen=True)
class BlockRead:
    """One block to read: per source, the split positions whose features it reads (source i reads
    `reads[i]`), and `owners`: the position whose low-dim row (or target) each frame goes with."""

    owners: np.ndarray
    reads: tuple[np.ndarray, ...]


def rows_by_block(rows: np.ndarray, block_frames: int) -> list[np.ndarray]:
    """The positions of a table whose cache rows are `rows`, grouped by cache block, in cache order."""
    positions = np.argsort(rows, kind="stable")
    blocks = rows[positions] // block_frames
    cuts = np.flatnonzero(np.diff(blocks)) + 1
    return [p for p in np.split(positions, cuts) if len(p)]


@dataclass
class Block:
    """What a worker hands over: features of the frames it read and kept, with the positions they go with."""

    owners: np.ndarray                 # [n] split positions (low-dim rows) the frames go with
    features: tuple[Features, ...]     # per source
    dropped: np.ndarray                # cache rows of the owners left out for NaN/inf features (drop_nonfinite)
    fetched: int = 0                   # bytes a worker's remote root copied locally for this block (a root read in
                                       # the consumer's process counts its own)
    verified: frozenset = field(default_factory=frozenset)  # cache blocks checked reading it


@dataclass(frozen=True)
class Failure:
    """A GraftcacheError raised in a worker, carried to the consumer as data."""

    kind: type
    message: str


@dataclass
class StreamStats:
    """What the consumer learns from the blocks it took: frames dropped for NaN/inf, bytes copied locally."""

    dropped: set[int] = field(default_factory=set)  # cache rows
    fetched: int = 0


class BlockStream(IterableDataset):
    """The blocks of `to_read`, once in their order (`seed` None), or forever in a new seeded order each epoch."""

    def __init__(self, low: LowDim, sources: Sequence[tuple[FeatureSource, np.ndarray]], to_read: Sequence[BlockRead],
                 *, seed: int | None = None, drop: bool = False, memo: BlockMemo | None = None) -> None:
        """`low`: the split the positions index; `sources`: (source, its cache row of every split position);
        `drop`: drop frames with NaN/inf features instead of refusing them; `memo`: blocks kept across streams
        when read in this process."""
        if seed is not None and not to_read:
            raise FitError("nothing to stream: the split has no frames")
        self.low, self.sources, self.to_read, self.seed, self.drop = low, tuple(sources), list(to_read), seed, drop
        self.memo = memo

    def __getstate__(self) -> dict:
        return {**self.__dict__, "memo": None}  # a worker reads for itself; the memo stays with its process

    def order(self) -> Iterator[BlockRead]:
        if self.seed is None:
            yield from self.to_read
            return
        for epoch in itertools.count():
            for i in np.random.default_rng((self.seed, epoch)).permutation(len(self.to_read)):
                yield self.to_read[i]

    def __iter__(self) -> Iterator[Block | Failure]:
        info = get_worker_info()
        worker, workers = (info.id, info.num_workers) if info is not None else (0, 1)
        for k, block in enumerate(self.order()):
            if k % workers != worker:
                continue
            try:
                yield self.read(block)
            except GraftcacheError as e:
                yield Failure(type(e), str(e))
                return

    def _checked(self) -> frozenset:
        """The blocks the readers of this stream's sources have checked."""
        return frozenset().union(*(src.reader.checks.done for src, _ in self.sources))

    def read(self, block: BlockRead) -> Block:
        before = self._checked()
        roots = [src.open().root for src, _ in self.sources] if get_worker_info() is not None else []
        fetched = sum(getattr(r, "fetched_bytes", 0) for r in roots)
        feats = tuple(self.memo.read(src, rows[pos]) if self.memo is not None else src.read(rows[pos])
                      for (src, rows), pos in zip(self.sources, block.reads, strict=True))
        bad = np.zeros(len(block.owners), dtype=bool)
        for (src, _), pos, per_camera in zip(self.sources, block.reads, feats, strict=True):
            for camera, values in per_camera.items():
                rows_bad = nonfinite_rows(values)
                if rows_bad.any() and not self.drop:
                    at = pos[int(np.flatnonzero(rows_bad)[0])]
                    raise FitError(nonfinite_message(src.key, f"features/{camera}", int(self.low.episode_index[at]),
                                                     int(self.low.frame_index[at]), f"{int(rows_bad.sum())} of "
                                                     f"the {len(pos)} frame(s) read with it"))
                bad |= rows_bad
        if bad.any():
            keep = torch.from_numpy(~bad)
            feats = tuple({c: v[keep] for c, v in per_camera.items()} for per_camera in feats)
        fetched = sum(getattr(r, "fetched_bytes", 0) for r in roots) - fetched
        return Block(block.owners[~bad], feats, self.low.rows[block.owners[bad]], fetched,
                     self._checked() - before)


def _fresh_context() -> multiprocessing.context.BaseContext:
    """Workers for an object-store root start from a fork server, not from this process: an object-store client
    runs a runtime of threads that a forked child lacks, so a worker forked from a process that already read
    the store waits forever on its first request (zarr's own event loop is reset at fork, local roots are safe
    to fork). The server imports the stream once; each worker is a cheap fork of it."""
    context = multiprocessing.get_context("forkserver")
    context.set_forkserver_preload([__name__])
    return context


def read_blocks(stream: BlockStream, num_workers: int, stats: StreamStats | None = None) -> Iterator[Block]:
    """The stream's blocks in order, read by `num_workers` prefetching processes (0: in this process). The blocks
    a worker checked count as checked by the sources' readers, so the next workers of this fit, which take the
    readers with the stream, do not check them again."""
    remote = any(is_url(src.root) for src, _ in stream.sources)
    loader = DataLoader(stream, batch_size=None, num_workers=num_workers,
                        worker_init_fn=single_thread_worker if num_workers else None,
                        prefetch_factor=PREFETCH_BLOCKS if num_workers else None,
                        multiprocessing_context=_fresh_context() if remote and num_workers else None)
    for item in loader:
        if isinstance(item, Failure):
            raise item.kind(item.message)
        if num_workers:
            for checks in {id(src.reader.checks): src.reader.checks for src, _ in stream.sources}.values():
                checks.update(item.verified)
        if stats is not None:
            stats.dropped.update(int(p) for p in item.dropped)
            stats.fetched += item.fetched
        yield item


class FrameQueue:
    """The frames of a block iterator as a queue: `take(k)` returns the next k (fewer only when the blocks end)."""

    def __init__(self, blocks: Iterator[Block], *, empty_limit: int | None = None) -> None:
        """`empty_limit`: this many blocks in a row with no frame left (all dropped) is an error, not a hang."""
        self._blocks, self._empty_limit = blocks, empty_limit
        self._block: Block | None = None
        self._at = 0

    def take(self, k: int) -> tuple[np.ndarray, tuple[Features, ...]] | None:
        """(owners [n], per-source features [n, ...]) of the next n = k frames; None when nothing is left."""
        owners, parts, empty = [], [], 0
        while k > 0:
            if self._block is None or self._at == len(self._block.owners):
                self._block, self._at = next(self._blocks, None), 0
                if self._block is None:
                    break
                empty = empty + 1 if not len(self._block.owners) else 0
                if self._empty_limit is not None and empty >= self._empty_limit:
                    raise FitError(f"{empty} blocks in a row kept no frame: every frame's features are NaN/inf")
                continue
            n = min(k, len(self._block.owners) - self._at)
            cut = slice(self._at, self._at + n)
            owners.append(self._block.owners[cut])
            parts.append(tuple({c: v[cut] for c, v in per.items()} for per in self._block.features))
            self._at += n
            k -= n
        if not owners:
            return None
        feats = tuple({c: torch.cat([p[i][c] for p in parts]) for c in parts[0][i]} for i in range(len(parts[0])))
        return np.concatenate(owners), feats
