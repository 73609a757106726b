"""A request resolved against its dataset and loaded encoder into a `Job` (cameras, episodes, grids,
the frames to cache), with every refusal that needs no decoding made here, before any work."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

import polars as pl

from graftcache.datasets import open_dataset
from graftcache.encoders import get_spec, load_encoder
from graftcache.errors import DatasetError, EncoderError, GraftcacheError
from graftcache.extract.job import Job
from graftcache.extract.provenance import build_index
from graftcache.extract.refusals import check_memory, check_policy_cameras
from graftcache.nonfinite import DROP_FLAG, KEEP_FLAG, lowdim_problem
from graftcache.pooling import format_grid, resolve_grids
from graftcache.requests import ExtractRequest
from graftcache.runtime import resolve_compute_dtype, resolve_device
from graftcache.store.cache import STORAGE_DTYPES


def resolve_job(req: ExtractRequest, log: Callable[[str], None]) -> Job:
    """Open the dataset, load the encoder and choose the frames; every refusal that needs no decoding is here."""
    device = resolve_device(req.device)
    req = replace(req, compute_dtype=resolve_compute_dtype(req.compute_dtype, device))  # never "auto" in a key
    if req.storage_dtype not in STORAGE_DTYPES:
        raise GraftcacheError(f"--storage-dtype {req.storage_dtype!r}: choose one of {', '.join(STORAGE_DTYPES)}")
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
    check_policy_cameras(req, encoder, cameras, meta.root, log)
    # "unpooled" -> the encoder's own grid (measured for native towers), so the key never depends on the spelling
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
    return Job(req, source, encoder, cameras, episodes, index, stream, device)
