"""Row-indexed reads from sharded caches (`FeatureCache.read_features(rows=...)`) equal numpy indexing, on the
first read of a block (whole block, checksum-checked) and on later ones (the rows' span only)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import polars as pl
import pytest
import torch
from helpers.caches import manifest

from graftcache.store import cache_key
from graftcache.store.cache import ArraySpec, FeatureCache

N, T, C = 100, 4, 3


def _cache(root: Path) -> tuple[FeatureCache, np.ndarray]:
    values = np.random.default_rng(0).standard_normal((N, T, C)).astype(np.float16)
    index = pl.DataFrame({"index": np.arange(N), "episode_index": np.arange(N) // 10, "frame_index": np.arange(N) % 10,
                          "task_index": np.zeros(N, int), "suite_index": np.zeros(N, int),
                          "timestamp": np.zeros(N), "state": [[0.0]] * N, "action": [[0.0]] * N})
    made = manifest(cameras=["image"], grids=["2x2"], n_frames=N)
    cache = FeatureCache.create(root / cache_key(made.to_dict()), made,
                                [ArraySpec("features/image/2x2", (T, C))], index, block_frames=32)
    for b in range(cache.layout["n_blocks"]):
        s, e = cache.block_range(b)
        cache.write_block(b, {"features/image/2x2": values[s:e]})
    cache.finalize()
    return cache, values


@pytest.mark.parametrize("rows", [
    np.array([37, 2, 2, 90, 64, 63, 0]),      # unsorted, repeated, across shard edges
    np.arange(10, 80),                          # a contiguous span over several shards
    np.array([99]),
    np.array([], dtype=np.int64),
])
def test_read_rows_equals_numpy_indexing(tmp_path, rows: np.ndarray) -> None:
    cache, values = _cache(tmp_path)
    for _ in range(2):  # first read checks whole blocks, the second reads spans of verified blocks
        got = cache.read_features("image", "2x2", rows)
        assert got.shape == (len(rows), T, C) and got.dtype == torch.float16
        np.testing.assert_array_equal(got.numpy(), values[rows])
