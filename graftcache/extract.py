"""Stage 1: decode every frame once, encode, and persist fp16 features with provenance: the encoder's own
patch grid (`--grids native`, the default) and any pooled grids asked for.

Data flow (forward only): worker processes decode whole episodes (PyAV / PNG, one thread each)
-> the main process fills a block buffer of `block_frames` frames -> the encoder runs on batches
inside the block -> the grids are written by a writer thread while the next block is encoded.
Blocks already marked done in the cache are never decoded again, so a rerun after Ctrl-C or
SIGKILL continues from what is durably written, and batch composition (aligned to blocks) is the
same as in an uninterrupted run, which makes the final bytes identical.
"""

from __future__ import annotations

import errno
import queue
import sys
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, replace
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
import polars as pl
import torch
from torch.utils.data import DataLoader, Dataset

import graftcache
from graftcache import budget
from graftcache.cameras import format_camera_map, match_cameras, renames
from graftcache.datasets import DatasetMeta, LeRobotSource, open_dataset, suite_of
from graftcache.datasets.suites import SUITES
from graftcache.encoders import get_spec, load_encoder
from graftcache.encoders.fingerprint import (
    MANIFEST_FIELD,
    NO_FINGERPRINT,
    compare,
    fingerprint,
    library_versions,
)
from graftcache.errors import CacheError, DatasetError, EncoderError, GraftcacheError
from graftcache.nonfinite import DROP_FLAG, KEEP_FLAG, lowdim_problem, nonfinite_rows
from graftcache.pooling import format_grid, parse_grid, pool_grid, resolve_grids
from graftcache.progress import progress
from graftcache.requests import ExtractRequest
from graftcache.runtime import (
    autocast,
    resolve_compute_dtype,
    resolve_device,
    resolve_dtype,
    set_main_threads,
    single_thread_worker,
)
from graftcache.store import FORMAT_VERSION, FeatureCache, Root, cache_key, open_root
from graftcache.store.cache import STORAGE_DTYPES, ArraySpec, from_storage, to_storage
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


def build_index(source: LeRobotSource, episodes: Sequence[int]) -> pl.DataFrame:
    """Per-frame index + low-dim table in cache order, with the LIBERO suite of each task."""
    table = source.lowdim(list(episodes))
    task_suite = [SUITES.index(suite_of(t)) for t in source.meta.tasks]
    return table.sort(["episode_index", "frame_index"]).with_columns(
        pl.col("task_index").map_elements(lambda i: task_suite[i], return_dtype=pl.Int64).alias("suite_index")
    )


def build_manifest(req: ExtractRequest, source: LeRobotSource, encoder: Any, episodes: Sequence[int],
                   cameras: Sequence[str], n_frames: int, numerics: dict[str, Any]) -> dict[str, Any]:
    """Provenance manifest. Identity fields (see store.key) decide the cache key; the numerics fingerprint
    (encoders/fingerprint.py) is not one of them: it decides whether this environment may extend the cache.
    `req.grids` are resolved names (never "native"); `native_grid` says which of them is the encoder's own grid,
    stored unpooled (None when only pooled grids are stored), for stage 2 to pool from. It is provenance: the
    encoder's grid and the stored grids, both in the key, already decide it."""
    meta = source.meta
    desc = encoder.describe()
    native = format_grid(encoder.spec.grid)
    winfo = dict(encoder.weights_info)
    extras = {name: list(shape) for name, shape in getattr(encoder, "extra_shapes", {}).items()}
    return {
        "format_version": FORMAT_VERSION,
        "graftcache_version": graftcache.__version__,
        "created_at": datetime.now(UTC).isoformat(timespec="seconds"),
        "dataset": {
            "source": str(req.dataset),
            "root": str(meta.root),
            "repo_id": meta.repo_id,
            "revision": meta.revision,
            "codebase_version": meta.codebase_version,
            "fps": meta.fps,
            "n_episodes_total": len(meta.episodes),
            "n_frames_total": meta.n_frames,
        },
        "dataset_fingerprint": meta.identity,
        "episodes": None if len(episodes) == len(meta.episodes) else [int(e) for e in episodes],
        "frame_stride": req.frame_stride,
        "cameras": list(cameras),
        "camera_keys": {c: meta.camera_keys[c] for c in cameras},
        "encoder": desc,
        "weights": winfo,
        "weights_sha256": winfo["sha256"],
        "random_init": bool(winfo.get("random_init", False)),
        "grids": list(req.grids),
        "native_grid": native if native in req.grids else None,
        "extras": extras,
        "dtype": req.dtype,
        "compute_dtype": req.compute_dtype,
        "n_frames": n_frames,
        "tasks": list(meta.tasks),
        "suites": list(SUITES),
        "state_key": meta.state_key,
        "action_key": meta.action_key,
        "versions": library_versions(),
        MANIFEST_FIELD: numerics,
        "run": {"device": req.device, "batch_size": req.batch_size, "num_workers": req.num_workers,
                "command": " ".join(sys.argv)},
        **req.extra_manifest,
    }


class _EpisodeFrames(Dataset):
    """Decodes one whole episode per item (all requested cameras) inside a worker process."""

    def __init__(self, source: LeRobotSource, episodes: Sequence[int], cameras: Sequence[str], stride: int) -> None:
        self.source, self.episodes, self.cameras, self.stride = source, list(episodes), list(cameras), stride
        self.lengths = {e.index: e.length for e in source.meta.episodes}

    def __len__(self) -> int:
        return len(self.episodes)

    def __getitem__(self, i: int) -> tuple[int, dict[str, np.ndarray] | str]:
        """(episode, frames), or (episode, one-line error text): an exception raised in a worker process
        would reach the main process wrapped in torch's multi-line "Caught ... in DataLoader worker"
        report, so decode errors travel back as values and are raised there as DatasetError."""
        ep = self.episodes[i]
        try:
            frames = self.source.decode_episode(ep, self.cameras)
            for cam, video in frames.items():
                if video.shape[0] != self.lengths[ep]:
                    raise DatasetError(f"{self.source.meta.root}: episode {ep} camera {cam} decoded "
                                       f"{video.shape[0]} frames, metadata says {self.lengths[ep]}")
            # keyframes only (frame_index % stride == 0), so only they cross the process boundary
            return ep, {cam: video[:: self.stride] for cam, video in frames.items()}
        except DatasetError as e:
            return ep, str(e)
        except Exception as e:  # a decoder library's own error on a damaged file
            return ep, f"{self.source.meta.root}: episode {ep}: cannot decode ({type(e).__name__}: {e})"


def _episode_stream(source: LeRobotSource, episodes: Sequence[int], cameras: Sequence[str], num_workers: int,
                    stride: int) -> Iterator[tuple[int, dict[str, np.ndarray]]]:
    ds = _EpisodeFrames(source, episodes, cameras, stride)
    items: Iterator[tuple[int, dict[str, np.ndarray] | str]] = (ds[i] for i in range(len(ds)))
    if num_workers:
        items = iter(DataLoader(ds, batch_size=None, shuffle=False, num_workers=num_workers,
                                worker_init_fn=single_thread_worker, prefetch_factor=2, persistent_workers=False,
                                multiprocessing_context="spawn" if sys.platform == "darwin" else None))
    for ep, frames in items:
        if isinstance(frames, str):
            raise DatasetError(" ".join(frames.split()))
        yield ep, frames


class _Writer:
    """Writes finished blocks on a background thread (Blosc and file I/O release the GIL), so
    encoding of block k+1 overlaps the compression and write of block k. At most one block waits."""

    def __init__(self, cache: FeatureCache) -> None:
        self.cache = cache
        self.queue: queue.Queue = queue.Queue(maxsize=1)
        self.error: BaseException | None = None
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        while (item := self.queue.get()) is not None:
            if self.error is None:
                try:
                    self.cache.write_block(*item)
                except BaseException as e:  # surfaced in the main thread by put()/close()
                    self.error = e

    def put(self, block: int, data: dict[str, np.ndarray]) -> None:
        if self.error:
            raise self.error
        self.queue.put((block, data))

    def close(self) -> None:
        self.queue.put(None)
        self.thread.join()
        if self.error:
            raise self.error


def encode_frames(encoder: Any, frames: np.ndarray, grids: Sequence[tuple[int, int]], *, batch_size: int,
                  device: torch.device, compute: torch.dtype, dtype: str) -> dict[str, np.ndarray]:
    """Encode uint8 frames [N,H,W,3] in batches; returns {grid name or extra name: stored array}."""
    outs: dict[str, list[np.ndarray]] = {}
    for s in range(0, len(frames), batch_size):
        x = torch.from_numpy(frames[s:s + batch_size]).to(device)
        with torch.inference_mode(), autocast(device, compute):
            grid, extras = encoder.forward_with_extras(encoder.preprocess(x))
        for g in grids:
            outs.setdefault(format_grid(g), []).append(to_storage(pool_grid(grid.float(), g), dtype))
        for name, tokens in extras.items():
            outs.setdefault(name, []).append(to_storage(tokens.float(), dtype))
    return {k: np.concatenate(v) for k, v in outs.items()}


def _plan(index: pl.DataFrame, cache: FeatureCache, todo: Sequence[int]) -> tuple[list[int], np.ndarray]:
    """Episodes that have frames in the blocks `todo`, and each cache row's block id."""
    bf = int(cache.layout["block_frames"])
    rows_block = np.arange(index.height) // bf
    needed = index.filter(pl.Series(np.isin(rows_block, list(todo))))["episode_index"].unique(maintain_order=True)
    return needed.to_list(), rows_block


def extract(req: ExtractRequest, log: Callable[[str], None] = print) -> ExtractResult:
    """Run stage 1 for one (dataset, encoder) request; reuse or resume the cache when it exists."""
    t0 = time.perf_counter()
    root = open_root(req.cache)  # a --cache that cannot be a root is refused before any work
    set_main_threads()
    device = resolve_device(req.device)
    req = replace(req, compute_dtype=resolve_compute_dtype(req.compute_dtype, device))  # never "auto" in a key
    compute = resolve_dtype(req.compute_dtype)
    if req.dtype not in STORAGE_DTYPES:
        raise GraftcacheError(f"--dtype {req.dtype!r}: choose one of {', '.join(STORAGE_DTYPES)}")
    source = open_dataset(req.dataset)
    meta = source.meta
    cameras = list(req.cameras or meta.cameras)
    for cam in cameras:
        if cam not in meta.cameras:
            raise DatasetError(f"{meta.root}: camera {cam!r} not in dataset; available: {', '.join(meta.cameras)}")
    all_eps = [e.index for e in meta.episodes]
    episodes = list(req.episodes) if req.episodes else all_eps
    unknown = sorted(set(episodes) - set(all_eps))
    if unknown:
        raise DatasetError(f"{meta.root}: episodes {unknown[:5]} not in dataset ({len(all_eps)} episodes)")
    episodes = sorted(set(episodes))

    spec = get_spec(req.encoder)
    if req.camera_map is not None and spec.library != "native":  # other encoders serve any policy's cameras
        raise EncoderError(f"encoder {spec.name!r} takes no --camera-map (only native towers do; `fit` takes the "
                           "map for the cache of any encoder)")
    encoder = load_encoder(spec, weights=req.weights, random_init=req.random_init, seed=req.seed,
                           device=device, policy=req.policy)
    _check_policy_cameras(req, encoder, cameras, meta.root, log)
    # "native" -> the encoder's own grid (measured for native towers), so the key never depends on the spelling
    req = replace(req, grids=tuple(map(format_grid, resolve_grids(req.grids, encoder.spec.grid))))
    chosen = set(episodes)
    n_frames = sum(-(-e.length // req.frame_stride) for e in meta.episodes if e.index in chosen)
    check_memory(req, meta, cameras, encoder.spec.width, n_frames, device)
    stream = build_index(source, episodes)
    problem = lowdim_problem(stream)
    if problem and not req.allow_nonfinite:
        raise DatasetError(f"{meta.root}: {problem}; nothing was cached. Exclude those episodes with --episodes, "
                           f"or pass {KEEP_FLAG} and drop the frames at fit with {DROP_FLAG}")
    if problem:
        log(f"note: keeping non-finite values ({KEEP_FLAG}): {problem}")
    index = stream.filter(pl.col("frame_index") % req.frame_stride == 0)
    manifest = build_manifest(req, source, encoder, episodes, cameras, index.height,
                              fingerprint(encoder, req.compute_dtype, device))
    key = cache_key(manifest)
    path = root.location(key)
    if manifest["random_init"]:
        log(f"note: encoder {spec.name} uses RANDOM-INIT weights (seed {req.seed}); the manifest says so")

    done = _complete(root, key, manifest, req)  # reusing takes no writer lock: a read-only root serves it
    if done is not None:
        _check_numerics(done, manifest, log)
    else:
        per_frame = len(cameras) * _stored_bytes(req, encoder.spec.width)
        _check_disk(root, key, manifest, req, per_frame, index.height)
        writing = _Writing(root, key, manifest, source, index, stream, encoder, cameras, req, device, compute, log, t0)
        result = writing.whole() if req.shard is None else writing.shard(*req.shard)
        if result is not None:
            return result
        done = FeatureCache.in_root(root, key)
    log(f"reusing complete cache {key} ({done.n_frames} frames)")
    return ExtractResult(key, path, True, done.n_frames, 0, time.perf_counter() - t0)


def _check_policy_cameras(req: ExtractRequest, encoder: Any, cameras: Sequence[str], root: Path,
                          log: Callable[[str], None]) -> None:
    """A native tower's cache is read by its own policy, camera by camera: refuse one whose cameras that policy
    cannot read (graftcache/cameras.py: by name, or as `camera_map` says) before decoding a frame."""
    policy = getattr(encoder, "policy_cameras", None)
    if policy is None:
        return
    mapping = match_cameras(policy, cameras, req.camera_map, policy_name=str(req.policy),
                            cache_name=f"dataset {root}" + (" (--cameras)" if req.cameras else ""))
    if renames(mapping):
        log(f"cameras mapped as asked (policy=dataset): {format_camera_map(mapping)}; `fit` takes the same map")


def _stored_bytes(req: ExtractRequest, width: int) -> int:
    """Bytes one camera's features of one frame take in the cache before compression (every stored grid)."""
    return sum(h * w for h, w in map(parse_grid, req.grids)) * width * STORAGE_DTYPES[req.dtype].itemsize


def check_memory(req: ExtractRequest, meta: DatasetMeta, cameras: Sequence[str], width: int, n_frames: int,
                 device: torch.device) -> None:
    """Refuse before any work an extraction whose blocks cannot be held: up to three blocks of stored features
    at once (one encoded, one queued, one being written; `_Writer`), a block of decoded frames, and a batch's
    grids pooled in fp32 (and their copy as the stored dtype). Encoder activations come on top."""
    block = min(req.block_frames, max(n_frames, 1))
    batch = min(req.batch_size, block)
    largest = max(h * w for h, w in map(parse_grid, req.grids))
    pixels = sum(int(np.prod(meta.image_shape[c])) for c in cameras)
    host = block * (3 * len(cameras) * _stored_bytes(req, width) + pixels)
    pooled = 2 * batch * largest * width * 4
    hint = "store coarser --grids (fits pool the encoder's own grid as they read it), or lower --block-frames"
    what = (f"{block} frames a block x {len(cameras)} camera(s) of grids {', '.join(req.grids)} x "
            f"{width} channels")
    if device.type == "cuda":
        budget.require(f"{what} (a batch of {batch} pooled on {device})", pooled,
                       *budget.available_memory(device), hint + " or --batch-size")
        pooled = 0
    budget.require(what, host + pooled, *budget.available_memory("cpu"), hint + " or --batch-size")


def _check_disk(root: Root, key: str, manifest: dict[str, Any], req: ExtractRequest, per_frame: int,
                n_frames: int) -> None:
    """Refuse before writing a cache whose unwritten frames cannot fit the free space of its file system
    (bytes before compression: features of float noise barely compress). Frames of blocks a matching
    unfinished cache already holds are not counted again."""
    free = budget.free_disk(root.location(key))
    if free is None:
        return
    todo = n_frames
    try:
        partial = FeatureCache.in_root(root, key)
        if partial.initialized and partial.matches(manifest):
            todo -= sum(stop - start for start, stop in map(partial.block_range, partial.blocks_done()))
    except CacheError:
        pass
    budget.require(f"cache {key}: {todo} frames x {per_frame} bytes a frame", todo * per_frame, free[0],
                   f"the free space of the file system of {root.location(key)}",
                   "free space, pick a --cache on a larger disk, or store coarser --grids or --dtype")


def shard_blocks(n_blocks: int, shard: int, shards: int) -> range:
    """Shard `shard` of `shards`: a contiguous range of blocks (the shards' ranges cover every block once and
    differ in size by one at most). Contiguous, because episodes cross block boundaries: a shard decodes
    every episode overlapping its blocks, and only those at its two ends are decoded by a neighbour too."""
    return range(shard * n_blocks // shards, (shard + 1) * n_blocks // shards)


@dataclass
class _Writing:
    """Writing the blocks of one cache that is not complete yet, by this process alone (`whole`) or as one of
    N shard processes (`shard`)."""

    root: Root
    key: str
    manifest: dict[str, Any]
    source: LeRobotSource
    index: pl.DataFrame
    stream: pl.DataFrame
    encoder: Any
    cameras: list[str]
    req: ExtractRequest
    device: torch.device
    compute: torch.dtype
    log: Callable[[str], None]
    t0: float

    def _waiting(self, who: str) -> None:
        self.log(f"waiting: {self.key} is being written by {who}")

    def _open(self) -> FeatureCache:
        return _open_or_create(self.root, self.key, self.manifest, self.index, self.stream, self.encoder,
                               self.cameras, self.req, self.log)

    def _fill(self, cache: FeatureCache, blocks: Sequence[int]) -> int:
        try:
            return _fill(cache, self.source, self.index, self.encoder, self.cameras, blocks, self.req, self.device,
                         self.compute)
        except OSError as e:
            if e.errno not in OUT_OF_SPACE:
                raise
            raise CacheError(_out_of_space(cache, e)) from None

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
        self.log(f"wrote {self.key}: {cache.n_frames} frames x {len(self.cameras)} cameras in {wall:.1f}s -> "
                 f"{self.root.location(self.key)}")
        return ExtractResult(self.key, self.root.location(self.key), False, cache.n_frames, encoded, wall, encode_s)


def _complete(root: Root, key: str, manifest: dict[str, Any], req: ExtractRequest) -> FeatureCache | None:
    """The finished cache of this request, opened read-only, or None when there is work to do."""
    try:
        cache = FeatureCache.in_root(root, key)
    except RefusedPlace:  # another cache under this key's name, a link: never reused, never replaced
        raise
    except CacheError:  # absent, or an initialisation that never wrote its manifest
        return None
    if not (cache.initialized and cache.complete and cache.matches(manifest)):
        return None
    cache.check_dataset(manifest["dataset_fingerprint"], req.dataset)
    return cache


def _open_or_create(root: Root, key: str, manifest: dict[str, Any], index: pl.DataFrame, stream: pl.DataFrame,
                    encoder: Any, cameras: Sequence[str], req: ExtractRequest,
                    log: Callable[[str], None]) -> FeatureCache:
    try:
        cache = FeatureCache.in_root(root, key, writable=True)
    except RefusedPlace:  # a cache this extraction did not make (copied or renamed here), a link: kept
        raise
    except CacheError:  # no readable zarr.json: an initialisation that never wrote it
        cache = None
    if cache is not None:
        if cache.initialized:  # never resume or reuse features of other data under this key (e.g. a copied cache)
            cache.check_dataset(manifest["dataset_fingerprint"], req.dataset)
        if cache.initialized and cache.matches(manifest):
            _check_numerics(cache, manifest, log)
            if not cache.complete:
                who = "resuming" if req.shard is None else f"shard {req.shard[0]}/{req.shard[1]} of"
                log(f"{who} {key}: {len(cache.blocks_done())}/{cache.layout['n_blocks']} blocks already written")
            return cache
        log(f"{key}: discarding an unfinished initialisation")
    width = encoder.spec.width
    grids = list(map(parse_grid, req.grids))
    arrays = [ArraySpec(f"features/{cam}/{format_grid(g)}", (g[0] * g[1], width)) for cam in cameras for g in grids]
    arrays += [ArraySpec(f"features/{cam}/{name}", tuple(shape))
               for cam in cameras for name, shape in manifest["extras"].items()]
    return FeatureCache.create(root.location(key), manifest, arrays, index, block_frames=req.block_frames,
                               action_stream=stream.select("episode_index", "frame_index", "action"), root=root)


def _check_numerics(cache: FeatureCache, manifest: dict[str, Any], log: Callable[[str], None]) -> None:
    """Resuming is refused when this environment computes other features than the one that began the cache
    (the fingerprint was just computed for `manifest`); reusing a complete cache only says so, since `fit`
    checks again and nothing is written here. A cache without a fingerprint (older graftcache) is used with a
    warning."""
    recorded = cache.manifest.get(MANIFEST_FIELD)
    if not recorded:
        log(f"warning: cache {cache.key}: {NO_FINGERPRINT}")
        return
    check = compare(cache.key, recorded, manifest[MANIFEST_FIELD], cache.manifest.get("versions"))
    if check.status == "match":
        return
    if cache.complete or check.status == "unchecked":
        log(f"warning: {check.line()}")
        return
    check.require_match(f"resuming would mix features of two environments in one cache; delete {cache.path} "
                        f"to re-extract it here")


def _fill(cache: FeatureCache, source: LeRobotSource, index: pl.DataFrame, encoder: Any, cameras: Sequence[str],
          blocks: Sequence[int], req: ExtractRequest, device: torch.device, compute: torch.dtype) -> int:
    """Decode the episodes of the unfinished blocks among `blocks`, encode block by block, hand blocks to the
    writer; returns the frames encoded."""
    todo = sorted(set(blocks) - cache.blocks_done())
    needed, rows_block = _plan(index, cache, todo)
    grids = list(map(parse_grid, req.grids))
    ep_rows = {ep: np.flatnonzero(index["episode_index"].to_numpy() == ep) for ep in needed}
    shapes = {cam: source.meta.image_shape[cam] for cam in cameras}
    buffers: dict[int, dict[str, np.ndarray]] = {}
    filled: dict[int, int] = {}
    todo_set = set(todo)
    writer = _Writer(cache)
    bar = progress(total=sum(cache.block_range(b)[1] - cache.block_range(b)[0] for b in todo), unit="frame",
                   desc=f"extract {cache.key}", enabled=req.progress)
    encoded = 0
    try:
        for ep, frames in _episode_stream(source, needed, cameras, req.num_workers, req.frame_stride):
            rows = ep_rows[ep]  # the episode's keyframes, in order: the decoded frames after the stride
            for block in np.unique(rows_block[rows]):
                block = int(block)
                if block not in todo_set:
                    continue
                start, stop = cache.block_range(block)
                buf = buffers.setdefault(block, {c: np.empty((stop - start, *shapes[c]), np.uint8) for c in cameras})
                sel = rows[(rows >= start) & (rows < stop)]
                src = sel - rows[0]
                for cam in cameras:
                    buf[cam][sel - start] = frames[cam][src]
                filled[block] = filled.get(block, 0) + len(sel)
                if filled[block] == stop - start:
                    buf = buffers.pop(block)
                    data = {f"features/{cam}/{name}": arr
                            for cam in cameras
                            for name, arr in encode_frames(encoder, buf[cam], grids, batch_size=req.batch_size,
                                                           device=device, compute=compute, dtype=req.dtype).items()}
                    if not req.allow_nonfinite:
                        _check_features(data, index, start, req.dtype, cache.key)
                    writer.put(block, data)
                    encoded += stop - start
                    bar.update(stop - start)
        writer.close()
    finally:
        bar.close()
    return encoded


def _check_features(data: dict[str, np.ndarray], index: pl.DataFrame, start: int, dtype: str, key: str) -> None:
    """EncoderError naming the first frame of a block whose stored features hold a NaN/inf (before the block
    is written, so the cache never holds it and is never marked complete)."""
    for name, values in data.items():
        bad = nonfinite_rows(from_storage(values, dtype))
        if bad.any():
            row = index.row(start + int(np.flatnonzero(bad)[0]), named=True)
            raise EncoderError(f"cache {key}: {name} is NaN/inf for episode {row['episode_index']} frame "
                               f"{row['frame_index']} ({int(bad.sum())} frame(s) in frames {start}-"
                               f"{start + len(bad) - 1}); the cache stays incomplete. Values past {dtype}'s range? "
                               f"try --dtype fp32, or pass {KEEP_FLAG} to keep them")


def _out_of_space(cache: FeatureCache, error: OSError) -> str:
    """One line for a full disk: how much the blocks still to write need (uncompressed bytes per frame, an upper
    bound: blocks already on disk say how well they compress), and that rerunning resumes."""
    done = cache.blocks_done()
    todo = [b for b in range(int(cache.layout["n_blocks"])) if b not in done]
    frames = sum(stop - start for start, stop in map(cache.block_range, todo))
    itemsize = STORAGE_DTYPES[cache.manifest["dtype"]].itemsize
    per_frame = sum(int(np.prod(shape)) * itemsize for shape in cache.layout["arrays"].values())
    where = f" writing {error.filename}" if error.filename else ""
    return (f"cache {cache.key}: {error.strerror}{where}; {frames} of {cache.n_frames} frames are not written yet, "
            f"needing up to {frames * per_frame / 2**20:.1f} MiB ({per_frame} bytes per frame before compression) on "
            f"the file system of {cache.path}. Blocks already written are kept: free space and run the same command "
            f"again to resume")
