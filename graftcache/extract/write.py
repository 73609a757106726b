"""The write protocol: reuse a complete cache, resume an unfinished one or create it, fill its blocks under the
root's writer lock (whole) or under a lock of one shard (`--shard i/N`), and publish `complete` last, only
while the lock is still held."""

from __future__ import annotations

import errno
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

from graftcache.encoders.fingerprint import compare
from graftcache.errors import CacheError
from graftcache.extract.blocks import fill
from graftcache.extract.job import Job, Target
from graftcache.extract.refusals import out_of_space
from graftcache.pooling import format_grid, parse_grid
from graftcache.store import FeatureCache, Manifest, Root
from graftcache.store.cache import ArraySpec
from graftcache.store.key import RefusedPlace

#: errnos of a full disk or quota: the extraction stops with a resumable one-line error.
OUT_OF_SPACE = frozenset({errno.ENOSPC, errno.EDQUOT})


@dataclass(frozen=True)
class ExtractResult:
    key: str
    path: Path | str  # a folder, or the URL of a cache in an object store
    reused: bool
    n_frames: int
    frames_encoded: int
    wall_s: float          # the whole call: opening the dataset, loading the encoder, encoding, finalising
    encode_s: float = 0.0  # decode + encode + write of the missing blocks (the steady-state part)
    complete: bool = True  # False only from a shard that finished its blocks while other shards' are missing


def shard_blocks(n_blocks: int, shard: int, shards: int) -> range:
    """Shard `shard` of `shards`: a contiguous range of blocks (the shards' ranges cover every block once and
    differ in size by one at most). Contiguous, because episodes cross block boundaries: a shard decodes
    every episode overlapping its blocks, and only those at its two ends are decoded by a neighbour too."""
    return range(shard * n_blocks // shards, (shard + 1) * n_blocks // shards)


@dataclass(frozen=True)
class Writing:
    """Writing the blocks of one cache that is not complete yet, by this process alone (`whole`) or as one of
    N shard processes (`shard`), under the root's writer locks."""

    target: Target
    job: Job
    log: Callable[[str], None]
    t0: float  # when the extraction began (its results' wall time)

    @property
    def key(self) -> str:
        return self.target.key

    @property
    def root(self) -> Root:
        return self.target.root

    def _waiting(self, who: str) -> None:
        self.log(f"waiting: {self.key} is being written by {who}")

    def _open(self) -> FeatureCache:
        return open_or_create(self.target, self.job, self.log)

    def _fill(self, cache: FeatureCache, blocks: Sequence[int]) -> int:
        try:
            return fill(cache, self.job, blocks)
        except OSError as e:
            if e.errno not in OUT_OF_SPACE:
                raise
            raise CacheError(out_of_space(cache, e)) from None

    def whole(self) -> ExtractResult | None:
        """Every block under the writer lock (held from initialisation to `complete`); None when another
        writer completed the cache meanwhile."""
        with self.root.writer(self.key, on_wait=self._waiting) as held:
            cache = self._open()
            if cache.complete:
                return None
            t_fill = time.perf_counter()
            encoded = self._fill(cache, range(int(cache.layout["n_blocks"])))
            encode_s = time.perf_counter() - t_fill
            held.check()  # an object-store lease can have been taken over: never publish over another writer
            cache.finalize()
        return self._wrote(cache, encoded, encode_s)

    def shard(self, shard: int, shards: int) -> ExtractResult | None:
        """The blocks of shard `shard` of `shards`, then `complete` if every shard's blocks are durable.

        The writer lock is held only to initialise the cache (exactly once: later shards find it initialised
        and check their numerics against its manifest) and to finalise it; the blocks are written under a
        lock of this shard alone (`<key>.shard-i-of-N`), so shards write concurrently and two processes never
        fill one shard. Whichever shard finds every block durable finalises, under the writer lock, after
        re-reading the attributes: a second finisher finds `complete` and does nothing. Rerunning a shard
        resumes it (written blocks are skipped). Shards of different N, or a whole run beside shards, would
        only write some blocks twice (the same bytes): fill one key either whole or as shards of one N."""
        with self.root.writer(self.key, on_wait=self._waiting):
            cache = self._open()
        if cache.complete:
            return None
        n_blocks = int(cache.layout["n_blocks"])
        mine = shard_blocks(n_blocks, shard, shards)
        name = f"{self.key}.shard-{shard}-of-{shards}"
        t_fill = time.perf_counter()
        with self.root.writer(name, on_wait=lambda who: self.log(f"waiting: shard {shard}/{shards} of {self.key} "
                                                                   f"is being written by {who}")):
            encoded = self._fill(cache, mine)
        encode_s = time.perf_counter() - t_fill
        missing = set(range(n_blocks)) - cache.blocks_done()
        if missing:
            unfinished = [i for i in range(shards) if missing & set(shard_blocks(n_blocks, i, shards))]
            self.log(f"shard {shard}/{shards} of {self.key}: its {len(mine)} block(s) are written; the cache still "
                     f"misses {len(missing)} of {n_blocks} blocks, of {len(unfinished)} of {shards} shards "
                     f"({', '.join(map(str, unfinished[:10]))}{', ...' if len(unfinished) > 10 else ''}); "
                     "the last shard to finish marks it complete")
            return ExtractResult(self.key, self.root.location(self.key), False, cache.n_frames, encoded,
                                 time.perf_counter() - self.t0, encode_s, complete=False)
        with self.root.writer(self.key, on_wait=self._waiting) as held:
            cache = FeatureCache.in_root(self.root, self.key, writable=True)  # attributes as they are now
            if cache.complete:
                self.log(f"shard {shard}/{shards} of {self.key}: another shard marked the cache complete")
            else:
                held.check()
                cache.finalize()
        return self._wrote(cache, encoded, encode_s)

    def _wrote(self, cache: FeatureCache, encoded: int, encode_s: float) -> ExtractResult:
        wall = time.perf_counter() - self.t0
        self.log(f"wrote {self.key}: {cache.n_frames} frames x {len(self.job.cameras)} cameras in {wall:.1f}s -> "
                 f"{self.root.location(self.key)}")
        return ExtractResult(self.key, self.root.location(self.key), False, cache.n_frames, encoded, wall, encode_s)


def find_complete(target: Target, job: Job) -> FeatureCache | None:
    """The finished cache of this job, opened read-only, or None when there is work to do."""
    root, key, manifest = target.root, target.key, target.manifest
    try:
        cache = FeatureCache.in_root(root, key)
    except RefusedPlace:  # another cache under this key's name, a link: never reused, never replaced
        raise
    except CacheError:  # absent, or an initialisation that never wrote its manifest
        return None
    if not (cache.initialized and cache.complete and cache.matches(manifest)):
        return None
    cache.check_dataset(manifest.dataset_identity, job.req.dataset)
    return cache


def open_or_create(target: Target, job: Job, log: Callable[[str], None]) -> FeatureCache:
    """The cache to write into: an unfinished one of this job to resume, else a new one (an initialisation that
    never finished is discarded)."""
    root, key, manifest, req, cameras = target.root, target.key, target.manifest, job.req, job.cameras
    try:
        cache = FeatureCache.in_root(root, key, writable=True)
    except RefusedPlace:  # a cache this extraction did not make (copied or renamed here), a link: kept
        raise
    except CacheError:  # no readable zarr.json: an initialisation that never wrote it
        cache = None
    if cache is not None:
        if cache.initialized:  # never resume or reuse features of other data under this key (e.g. a copied cache)
            cache.check_dataset(manifest.dataset_identity, req.dataset)
        if cache.initialized and cache.matches(manifest):
            check_numerics(cache, manifest, log)
            if not cache.complete:
                who = "resuming" if req.shard is None else f"shard {req.shard[0]}/{req.shard[1]} of"
                log(f"{who} {key}: {len(cache.blocks_done())}/{cache.layout['n_blocks']} blocks already written")
            return cache
        log(f"{key}: discarding an unfinished initialisation")
    width = job.encoder.spec.width
    grids = list(map(parse_grid, req.grids))
    arrays = [ArraySpec(f"features/{cam}/{format_grid(g)}", (g[0] * g[1], width)) for cam in cameras for g in grids]
    arrays += [ArraySpec(f"features/{cam}/{name}", tuple(shape))
               for cam in cameras for name, shape in manifest.extras.items()]
    return FeatureCache.create(root.location(key), manifest, arrays, job.index, block_frames=req.block_frames,
                               action_stream=job.stream.select("episode_index", "frame_index", "action"), root=root)


def check_numerics(cache: FeatureCache, manifest: Manifest, log: Callable[[str], None]) -> None:
    """Resuming is refused when this environment computes other features than the one that began the cache
    (the fingerprint was just computed for `manifest`); reusing a complete cache only says so, since `fit`
    checks again and nothing is written here."""
    check = compare(cache.key, cache.manifest.numerics, manifest.numerics, cache.manifest.versions)
    if check.status == "match":
        return
    if cache.complete or check.status == "unchecked":
        log(f"warning: {check.line()}")
        return
    check.require_match(f"resuming would mix features of two environments in one cache; delete {cache.path} "
                        f"to re-extract it here")
