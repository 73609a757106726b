"""Refusals before work (memory, disk, a native tower's cameras) and the one-line texts of failures during it
(NaN/inf features, a full disk)."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import polars as pl
import torch

from graftcache import budget
from graftcache.cameras import format_camera_map, match_cameras, renames
from graftcache.datasets import DatasetMeta
from graftcache.errors import CacheError, EncoderError
from graftcache.nonfinite import KEEP_FLAG, nonfinite_rows
from graftcache.pooling import parse_grid
from graftcache.requests import ExtractRequest
from graftcache.store import FeatureCache
from graftcache.store.cache import STORAGE_DTYPES, from_storage

if TYPE_CHECKING:
    from graftcache.extract.job import Job, Target


def check_policy_cameras(req: ExtractRequest, encoder: Any, cameras: Sequence[str], root: Path,
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


def stored_bytes(req: ExtractRequest, width: int) -> int:
    """Bytes one camera's features of one frame take in the cache before compression (every stored grid)."""
    return sum(h * w for h, w in map(parse_grid, req.grids)) * width * STORAGE_DTYPES[req.storage_dtype].itemsize


def check_memory(req: ExtractRequest, meta: DatasetMeta, cameras: Sequence[str], width: int, n_frames: int,
                 device: torch.device) -> None:
    """Refuse before any work an extraction whose blocks cannot be held: up to three blocks of stored features
    at once (one encoded, one queued, one being written; `BlockWriter`), a block of decoded frames, and a batch's
    grids pooled in fp32 (and their copy as the stored dtype). Encoder activations come on top."""
    block = min(req.block_frames, max(n_frames, 1))
    batch = min(req.batch_size, block)
    largest = max(h * w for h, w in map(parse_grid, req.grids))
    pixels = sum(int(np.prod(meta.image_shape[c])) for c in cameras)
    host = block * (3 * len(cameras) * stored_bytes(req, width) + pixels)
    pooled = 2 * batch * largest * width * 4
    hint = "store coarser --grids (fits pool the encoder's own grid as they read it), or lower --block-frames"
    what = (f"{block} frames a block x {len(cameras)} camera(s) of grids {', '.join(req.grids)} x "
            f"{width} channels")
    if device.type == "cuda":
        budget.require(f"{what} (a batch of {batch} pooled on {device})", pooled,
                       *budget.available_memory(device), hint + " or --batch-size")
        pooled = 0
    budget.require(what, host + pooled, *budget.available_memory("cpu"), hint + " or --batch-size")


def check_disk(target: Target, job: Job) -> None:
    """Refuse before writing a cache whose unwritten frames cannot fit the free space of its file system
    (bytes before compression: features of float noise barely compress). Frames of blocks a matching
    unfinished cache already holds are not counted again."""
    root, key = target.root, target.key
    free = budget.free_disk(root.location(key))
    if free is None:
        return
    todo = job.index.height
    try:
        partial = FeatureCache.in_root(root, key)
        if partial.initialized and partial.matches(target.manifest):
            todo -= sum(stop - start for start, stop in map(partial.block_range, partial.blocks_done()))
    except CacheError:
        pass
    per_frame = len(job.cameras) * stored_bytes(job.req, job.encoder.spec.width)
    budget.require(f"cache {key}: {todo} frames x {per_frame} bytes a frame", todo * per_frame, free[0],
                   f"the free space of the file system of {root.location(key)}",
                   "free space, pick a --cache on a larger disk, or store coarser --grids or --storage-dtype")


def check_features(data: dict[str, np.ndarray], index: pl.DataFrame, start: int, dtype: str, key: str) -> None:
    """EncoderError naming the first frame of a block whose stored features hold a NaN/inf (before the block
    is written, so the cache never holds it and is never marked complete)."""
    for name, values in data.items():
        bad = nonfinite_rows(from_storage(values, dtype))
        if bad.any():
            row = index.row(start + int(np.flatnonzero(bad)[0]), named=True)
            raise EncoderError(f"cache {key}: {name} is NaN/inf for episode {row['episode_index']} frame "
                               f"{row['frame_index']} ({int(bad.sum())} frame(s) in frames {start}-"
                               f"{start + len(bad) - 1}); the cache stays incomplete. Values past {dtype}'s range? "
                               f"try --storage-dtype fp32, or pass {KEEP_FLAG} to keep them")


def out_of_space(cache: FeatureCache, error: OSError) -> str:
    """One line for a full disk: how much the blocks still to write need (uncompressed bytes per frame, an upper
    bound: blocks already on disk say how well they compress), and that rerunning resumes."""
    done = cache.blocks_done()
    todo = [b for b in range(int(cache.layout["n_blocks"])) if b not in done]
    frames = sum(stop - start for start, stop in map(cache.block_range, todo))
    itemsize = STORAGE_DTYPES[cache.manifest.storage_dtype].itemsize
    per_frame = sum(int(np.prod(shape)) * itemsize for shape in cache.layout["arrays"].values())
    where = f" writing {error.filename}" if error.filename else ""
    return (f"cache {cache.key}: {error.strerror}{where}; {frames} of {cache.n_frames} frames are not written yet, "
            f"needing up to {frames * per_frame / 2**20:.1f} MiB ({per_frame} bytes per frame before compression) on "
            f"the file system of {cache.path}. Blocks already written are kept: free space and run the same command "
            f"again to resume")
