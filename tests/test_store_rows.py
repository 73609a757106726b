"""Row-indexed reads from sharded caches (`FeatureCache.read_features(rows=...)`) equal numpy indexing."""

from __future__ import annotations

import numpy as np
import pytest
import zarr

from graftcache.store.cache import _take_rows


@pytest.mark.parametrize("rows", [
    np.array([37, 2, 2, 90, 64, 63, 0]),      # unsorted, repeated, across shard edges
    np.arange(10, 80),                          # a contiguous span over several shards
    np.array([99]),
    np.array([], dtype=np.int64),
])
def test_take_rows_equals_numpy_indexing(tmp_path, rows: np.ndarray) -> None:
    values = np.random.default_rng(0).standard_normal((100, 4, 3)).astype(np.float16)
    arr = zarr.create_array(tmp_path / "a.zarr", shape=values.shape, dtype=values.dtype, chunks=(8, 4, 3),
                            shards=(32, 4, 3))
    arr[...] = values
    got = _take_rows(arr, rows, block_frames=32)
    assert got.shape == (len(rows), 4, 3) and got.dtype == np.float16
    np.testing.assert_array_equal(got, values[rows])
