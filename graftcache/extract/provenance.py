"""What a cache records about its frames: the per-frame index with low-dim columns (`build_index`) and the
manifest (`build_manifest`, a graftcache.store.Manifest)."""

from __future__ import annotations

import sys
from collections.abc import Sequence
from datetime import UTC, datetime
from typing import TYPE_CHECKING, Any

import polars as pl

import graftcache
from graftcache.datasets import LeRobotSource, suite_of
from graftcache.datasets.suites import SUITES
from graftcache.encoders.fingerprint import library_versions
from graftcache.pooling import format_grid
from graftcache.store import FORMAT_VERSION, DatasetRecord, Manifest

if TYPE_CHECKING:
    from graftcache.extract.job import Job


def build_index(source: LeRobotSource, episodes: Sequence[int]) -> pl.DataFrame:
    """Per-frame index + low-dim table in cache order, with the LIBERO suite of each task."""
    table = source.lowdim(list(episodes))
    task_suite = [SUITES.index(suite_of(t)) for t in source.meta.tasks]
    return table.sort(["episode_index", "frame_index"]).with_columns(
        pl.col("task_index").map_elements(lambda i: task_suite[i], return_dtype=pl.Int64).alias("suite_index")
    )


def build_manifest(job: Job, numerics: dict[str, Any]) -> Manifest:
    """Provenance manifest. Identity fields (see store.key) decide the cache key; the numerics fingerprint
    (encoders/fingerprint.py) is not one of them: it decides whether this environment may extend the cache.
    `req.grids` are resolved names (never "unpooled"); `unpooled_grid` says which of them is the encoder's own grid,
    stored unpooled (None when only pooled grids are stored), for stage 2 to pool from. It is provenance: the
    encoder's grid and the stored grids, both in the key, already decide it."""
    req, meta, encoder = job.req, job.source.meta, job.encoder
    unpooled = format_grid(encoder.spec.grid)
    winfo = dict(encoder.weights_info)
    extras = {name: list(shape) for name, shape in getattr(encoder, "extra_shapes", {}).items()}
    return Manifest(
        format_version=FORMAT_VERSION,
        graftcache_version=graftcache.__version__,
        created_at=datetime.now(UTC).isoformat(timespec="seconds"),
        dataset=DatasetRecord(source=str(req.dataset), root=str(meta.root), repo_id=meta.repo_id,
                              revision=meta.revision, codebase_version=meta.codebase_version, fps=meta.fps,
                              n_episodes_total=len(meta.episodes), n_frames_total=meta.n_frames),
        dataset_identity=meta.identity,
        episodes=None if len(job.episodes) == len(meta.episodes) else [int(e) for e in job.episodes],
        frame_stride=req.frame_stride,
        cameras=list(job.cameras),
        camera_keys={c: meta.camera_keys[c] for c in job.cameras},
        encoder=encoder.describe(),
        weights=winfo,
        weights_sha256=winfo["sha256"],
        random_init=bool(winfo.get("random_init", False)),
        grids=list(req.grids),
        unpooled_grid=unpooled if unpooled in req.grids else None,
        extras=extras,
        storage_dtype=req.storage_dtype,
        compute_dtype=req.compute_dtype,
        n_frames=job.index.height,
        tasks=list(meta.tasks),
        suites=list(SUITES),
        state_key=meta.state_key,
        action_key=meta.action_key,
        versions=library_versions(),
        numerics=numerics,
        run={"device": req.device, "batch_size": req.batch_size, "num_workers": req.num_workers,
             "command": " ".join(sys.argv)},
        extra=dict(req.extra_manifest),
    )


def weights_note(manifest: Manifest) -> str | None:
    """The line that says an encoder's weights are not pretrained ones, and which fact holds: random-init (with its
    seed, or the policy whose tower it is) or trained by train-tiny (None: real weights)."""
    name, weights = manifest.encoder_name, manifest.weights
    if manifest.trained_by is not None:
        return (f"note: encoder {name} is the tower of a policy trained by {manifest.trained_by} ({weights['ref']}), "
                "not released weights; the manifest says so")
    if not manifest.random_init:
        return None
    whose = f"policy {weights['ref']}" if weights.get("source") == "policy" else f"seed {weights.get('seed')}"
    return f"note: encoder {name} uses RANDOM-INIT weights ({whose}); the manifest says so"
