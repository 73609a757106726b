"""Feature caches for tests and benchmarks: synthetic ones written with the store's own writer by `write_cache`
(seeded random features at any size, real index / low-dim / action-stream columns, for stage 2's data path
without an encoder), a copy of a cache whose manifest says other settings (`rekeyed`; helpers.previous_formats
builds caches of an older format on it), and comparing two caches file by file (a folder, or the objects of a
bucket under a key)."""

from __future__ import annotations

import json
import math
import shutil
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import polars as pl

import graftcache
from graftcache.store import FORMAT_VERSION, DatasetRecord, FeatureCache, Manifest, cache_key
from graftcache.store.cache import ArraySpec
from graftcache.store.key import IDENTITY_FIELDS
from graftcache.store.manifest import stored_key

SUITES = ["libero_spatial", "libero_object", "libero_goal", "libero_10", "libero_90", "unknown"]
TASKS = ["put the bowl on the plate", "open the drawer", "turn on the stove"]
CAMERAS = ("image", "image2")


def manifest(**over: Any) -> Manifest:
    """A complete manifest of this format for a cache written without an encoder: `over` replaces fields
    (`dataset` as a dict of the DatasetRecord fields to replace)."""
    dataset = {"source": "synthetic", "root": "synthetic", "repo_id": None, "revision": None,
               "codebase_version": "v3.0", "fps": 10, "n_episodes_total": 0, "n_frames_total": 0,
               **over.pop("dataset", {})}
    fields: dict[str, Any] = {
        "format_version": FORMAT_VERSION, "graftcache_version": graftcache.__version__,
        "created_at": "2026-01-01T00:00:00+00:00", "dataset_identity": {"codebase_version": "v3.0", "files": {}},
        "episodes": None, "frame_stride": 1, "cameras": list(CAMERAS), "encoder": {"name": "synthetic", "width": 8},
        "weights": {"source": "random-init", "seed": 0, "sha256": "0" * 64}, "weights_sha256": "0" * 64,
        "random_init": True, "grids": ["4x4"], "unpooled_grid": None, "extras": {}, "storage_dtype": "fp16",
        "compute_dtype": "fp32", "n_frames": 0, "tasks": TASKS, "suites": SUITES, "state_key": "observation.state",
        "action_key": "action", "versions": {}, "numerics": {}, "run": {}, **over}
    fields.setdefault("camera_keys", {c: f"observation.images.{c}" for c in fields["cameras"]})
    return Manifest(dataset=DatasetRecord(**dataset), **fields)


def write_cache(root: Path, made: Manifest, index: pl.DataFrame, *, block_frames: int,
                features: Callable[[int, int, str], np.ndarray]) -> FeatureCache:
    """The one synthetic-cache writer (tests and benchmarks): a complete cache of `made` (its one grid, every
    camera, `made.encoder["width"]` wide) under `root` in the folder of its key, written with the store's own
    writer, block by block, camera by camera: `features(start, stop, camera)` gives rows start..stop."""
    (name,) = made.grids
    tokens = math.prod(int(n) for n in name.split("x"))
    path = root / cache_key(made.to_dict())
    cache = FeatureCache.create(path, made, [ArraySpec(f"features/{c}/{name}", (tokens, made.encoder["width"]))
                                             for c in made.cameras], index, block_frames=block_frames)
    for b in range(cache.layout["n_blocks"]):
        start, stop = cache.block_range(b)
        cache.write_block(b, {f"features/{c}/{name}": features(start, stop, c) for c in made.cameras})
    cache.finalize()
    return FeatureCache(path, writable=False)


def synthetic_cache(root: Path, lengths: Sequence[int], *, grid: tuple[int, int] = (4, 4), width: int = 8,
                    block_frames: int = 8, state_dim: int = 8, action_dim: int = 7, seed: int = 0,
                    nan_at: tuple[int, int] | None = None) -> FeatureCache:
    """A complete fp16 cache under `root` (in the folder of its key) of episodes of `lengths` (task = episode
    % 3, all libero_spatial), features N(0, 1) at `grid`; `nan_at` (episode, frame) puts a NaN into that
    frame's `image` features."""
    rng = np.random.default_rng(seed)
    episode = np.repeat(np.arange(len(lengths)), lengths)
    frame = np.concatenate([np.arange(n) for n in lengths])
    n = len(episode)
    index = pl.DataFrame({
        "index": np.arange(n), "episode_index": episode, "frame_index": frame, "task_index": episode % len(TASKS),
        "suite_index": np.zeros(n, dtype=np.int64), "timestamp": frame / 10.0,
        "state": rng.standard_normal((n, state_dim)).astype(np.float32),
        "action": rng.standard_normal((n, action_dim)).astype(np.float32),
    }).with_columns(pl.col("state").cast(pl.Array(pl.Float32, state_dim)),
                    pl.col("action").cast(pl.Array(pl.Float32, action_dim)))
    made = manifest(encoder={"name": "synthetic", "width": width}, grids=[f"{grid[0]}x{grid[1]}"], n_frames=n)
    nan_row = None if nan_at is None else int(np.flatnonzero((episode == nan_at[0]) & (frame == nan_at[1]))[0])

    def features(start: int, stop: int, camera: str) -> np.ndarray:
        x = rng.standard_normal((stop - start, grid[0] * grid[1], width)).astype(np.float16)
        if camera == "image" and nan_row is not None and start <= nan_row < stop:
            x[nan_row - start, 0, 0] = np.nan
        return x

    return write_cache(root, made, index, block_frames=block_frames, features=features)


def dataset_cache(root: Path, dataset: str | Path, suite: str | None, *, grid: tuple[int, int], width: int,
                  block_frames: int = 256) -> FeatureCache:
    """A complete fp16 cache under `root` (in the folder of its key) of `dataset`'s `suite` episodes (None: all)
    as `extract` lays it out (the dataset's own index, low-dim and action columns), with seeded random features
    at `grid`, `width` wide, for every camera: what a fit reads of a real cache, without paying for decoding
    and encoding (the fit cannot tell the difference).
    One random block is written for every block (memory, read and copy costs do not depend on the values)."""
    from graftcache.datasets import open_dataset, suite_of
    from graftcache.datasets.suites import SUITES
    from graftcache.extract import build_index

    source = open_dataset(str(dataset))
    meta = source.meta
    episodes = [e.index for e in meta.episodes if suite is None or suite_of(meta.tasks[e.task_index]) == suite]
    index = build_index(source, episodes)
    made = manifest(encoder={"name": f"synthetic-{width}", "width": width}, cameras=list(meta.cameras),
                    grids=[f"{grid[0]}x{grid[1]}"], suites=list(SUITES), tasks=list(meta.tasks), n_frames=index.height,
                    dataset={"source": str(dataset), "root": str(meta.root)})
    block = np.random.default_rng(0).standard_normal((block_frames, grid[0] * grid[1], width)).astype(np.float16)
    return write_cache(root, made, index, block_frames=block_frames,
                       features=lambda start, stop, _: block[:stop - start])


def rekeyed(folder: Path, root: Path, edit: Callable[[dict], dict]) -> Path:
    """Where a copy of the cache in `folder` whose manifest is `edit(manifest as stored)` now lies, under `root`
    in the folder of the key that manifest hashes to: a cache made with those settings as far as its folder name
    and manifest go (its arrays are `folder`'s)."""
    return _restored(folder, root, edit)


def _restored(folder: Path, root: Path, edit: Callable[[dict], dict]) -> Path:
    staging = root / ".staging" / folder.name
    shutil.copytree(folder, staging)
    meta = json.loads((staging / "zarr.json").read_text())
    meta["attributes"]["manifest"] = stored = edit(meta["attributes"]["manifest"])
    (staging / "zarr.json").write_text(json.dumps(meta))
    try:
        target = root / stored_key(stored)  # as graftcache names the folder of a manifest of that format
    except KeyError:  # a format no graftcache reads: any folder of a key's shape
        target = root / cache_key({**dict.fromkeys(IDENTITY_FIELDS), **stored})
    staging.rename(target)
    shutil.rmtree(root / ".staging")
    return target


#: Group attributes that record when and how a run happened, not what it computed: two runs of one request
#: (one process or several shards, here or into a bucket) differ in these and nothing else.
RUN_ATTRIBUTES = ("completed_at",)
RUN_MANIFEST_FIELDS = ("created_at", "run")


def folder_files(folder: Path) -> dict[str, bytes]:
    """Every file under a cache folder, by its '/'-separated path inside it."""
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in folder.rglob("*") if p.is_file()}


def assert_same_cache(got: Mapping[str, bytes], want: Mapping[str, bytes]) -> None:
    """The same files with the same bytes, except the group's zarr.json, whose attributes may differ only in
    RUN_ATTRIBUTES and the manifest's RUN_MANIFEST_FIELDS (each present on both sides)."""
    assert set(got) == set(want)
    assert any(rel.startswith("features/") for rel in want)
    for rel in set(want) - {"zarr.json"}:
        assert got[rel] == want[rel], rel
    attrs = [json.loads(files["zarr.json"])["attributes"] for files in (got, want)]
    for a in attrs:
        assert all(a.pop(name) for name in RUN_ATTRIBUTES)
        assert all(a["manifest"].pop(name) for name in RUN_MANIFEST_FIELDS)
    assert attrs[0] == attrs[1]
