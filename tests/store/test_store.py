"""Cache store: layout, checksums, completeness, key identity, locking."""

from __future__ import annotations

import multiprocessing as mp
from pathlib import Path

import numpy as np
import polars as pl
import pytest
import torch
from helpers.caches import manifest

from graftcache.errors import CacheError
from graftcache.store import FeatureCache, Manifest, cache_key, cache_root, list_caches
from graftcache.store.cache import ArraySpec, from_storage, to_storage
from graftcache.store.lock import exclusive

N, T, C = 70, 4, 6


def _index(n: int = N) -> pl.DataFrame:
    rng = np.random.default_rng(0)
    return pl.DataFrame({
        "index": np.arange(n), "episode_index": np.arange(n) // 10, "frame_index": np.arange(n) % 10,
        "task_index": (np.arange(n) // 20) % 2, "suite_index": np.zeros(n, int),
        "timestamp": (np.arange(n) % 10) / 10.0,
        "state": rng.random((n, 8), dtype=np.float32).tolist(), "action": rng.random((n, 7), dtype=np.float32).tolist(),
    })


def _manifest(**over) -> Manifest:
    return manifest(**{"dataset_identity": {"files": {"meta/info.json": {"sha256": "a"}}}, "cameras": ["image"],
                       "encoder": {"name": "toy", "model_id": "x"}, "weights_sha256": "w", "grids": ["2x2"],
                       "n_frames": N, "run": {"batch_size": 8}, **over})


def _key(**over) -> str:
    return cache_key(_manifest(**over).to_dict())


def _at(root: Path, **over) -> Path:
    """Where a cache of `_manifest(**over)` lives under `root`: the folder named by its key."""
    return root / _key(**over)


def _filled(root: Path, dtype: str = "fp16") -> tuple[FeatureCache, np.ndarray]:
    cache = FeatureCache.create(_at(root, storage_dtype=dtype), _manifest(storage_dtype=dtype),
                                [ArraySpec("features/image/2x2", (T, C))], _index(), block_frames=32)
    data = torch.randn(N, T, C, generator=torch.Generator().manual_seed(1))
    for b in range(cache.layout["n_blocks"]):
        s, e = cache.block_range(b)
        cache.write_block(b, {"features/image/2x2": to_storage(data[s:e], dtype)})
    return cache, data


def test_roundtrip_and_verify(tmp_path: Path) -> None:
    cache, data = _filled(tmp_path)
    assert cache.layout["n_blocks"] == 3 and cache.block_range(2) == (64, 70)
    assert not cache.complete
    cache.finalize()
    assert cache.complete and cache.verify() == []
    got = FeatureCache(_at(tmp_path)).read_features("image", "2x2")
    assert got.dtype == torch.float16 and got.shape == (N, T, C)
    assert torch.equal(got, data.half())
    rows = cache.read_features("image", "2x2", np.array([3, 40, 69]))
    assert torch.equal(rows, data.half()[[3, 40, 69]])
    idx = cache.index()
    assert idx.height == N and idx["episode_index"].to_list() == (np.arange(N) // 10).tolist()
    assert np.allclose(np.stack(idx["state"].to_numpy()), np.asarray(_index()["state"].to_list()))


def test_bf16_storage_roundtrip(tmp_path: Path) -> None:
    cache, data = _filled(tmp_path, dtype="bf16")
    cache.finalize()
    got = cache.read_features("image", "2x2")
    assert got.dtype == torch.bfloat16 and torch.equal(got, data.bfloat16())
    assert torch.equal(from_storage(to_storage(data, "bf16"), "bf16"), data.bfloat16())


def test_finalize_refuses_missing_blocks(tmp_path: Path) -> None:
    cache = FeatureCache.create(_at(tmp_path), _manifest(), [ArraySpec("features/image/2x2", (T, C))],
                                _index(), block_frames=32)
    cache.write_block(0, {"features/image/2x2": np.zeros((32, T, C), np.float16)})
    with pytest.raises(CacheError, match=r"blocks \[1, 2\] not written"):
        cache.finalize()
    assert not cache.complete
    assert "incomplete (2 of 3 blocks not written)" in cache.verify()[0]


def test_verify_detects_corruption(tmp_path: Path) -> None:
    cache, _ = _filled(tmp_path)
    cache.finalize()
    arr = cache.group["features/image/2x2"]
    arr[40] = np.ones((T, C), np.float16)  # silent change after completion
    problems = FeatureCache(cache.path).verify()
    assert problems == [f"{cache.key}: features/image/2x2 frames 32-63 checksum mismatch "
                        "(block 1, features/image/2x2/c/1/0/0)"]


def test_write_block_rejects_wrong_shapes(tmp_path: Path) -> None:
    cache = FeatureCache.create(_at(tmp_path), _manifest(), [ArraySpec("features/image/2x2", (T, C))],
                                _index(), block_frames=32)
    with pytest.raises(CacheError, match="block 2 of features/image/2x2 has 32 frames, expected 6"):
        cache.write_block(2, {"features/image/2x2": np.zeros((32, T, C), np.float16)})
    with pytest.raises(CacheError, match="expected"):
        cache.write_block(0, {"features/other/2x2": np.zeros((32, T, C), np.float16)})


def test_key_ignores_provenance_but_not_numbers() -> None:
    base = _key()
    assert base.startswith("toy-")
    assert _key(run={"batch_size": 64, "num_workers": 0}) == base
    assert _key(created_at="later") == base
    for change in ({"grids": ["4x4"]}, {"storage_dtype": "bf16"}, {"weights_sha256": "v"}, {"episodes": [0, 1]},
                   {"cameras": ["image", "image2"]}, {"compute_dtype": "bf16"},
                   {"dataset_identity": {"files": {"meta/info.json": {"sha256": "b"}}}}):
        assert _key(**change) != base, change


def test_cache_root_resolution(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    assert cache_root(tmp_path / "x") == tmp_path / "x"
    monkeypatch.setenv("GRAFTCACHE_HOME", str(tmp_path / "env"))
    assert cache_root() == tmp_path / "env"
    monkeypatch.delenv("GRAFTCACHE_HOME")
    assert cache_root() == Path.home() / ".cache" / "graftcache"


def test_list_caches_skips_other_folders(tmp_path: Path) -> None:
    cache, _ = _filled(tmp_path)
    (tmp_path / "not-a-cache").mkdir()
    assert [c.key for c in list_caches(tmp_path)] == [cache.key]
    assert list_caches(tmp_path / "absent") == []


def _hold(path: str, ready, release) -> None:
    with exclusive(Path(path)):
        ready.set()
        release.wait(10)


def test_lock_excludes_second_writer(tmp_path: Path) -> None:
    ctx = mp.get_context("spawn")
    ready, release = ctx.Event(), ctx.Event()
    proc = ctx.Process(target=_hold, args=(str(tmp_path / "k.lock"), ready, release))
    proc.start()
    try:
        assert ready.wait(30)
        with pytest.raises(CacheError, match=rf"being written by another process \(pid {proc.pid}\)"):
            with exclusive(tmp_path / "k.lock", wait=False):
                pass
    finally:
        release.set()
        proc.join(10)
    with exclusive(tmp_path / "k.lock", wait=False):  # free again: taken without waiting (wait=False raises if held)
        pass


def test_a_manifest_is_read_typed_and_a_wrong_field_is_refused_by_name() -> None:
    stored = _manifest().to_dict()
    assert Manifest.read(stored, "here", "k") == _manifest()
    for edit, says in ((lambda m: m["dataset"].update(fps="ten"), "field dataset.fps is 'ten', not float"),
                       (lambda m: m.update(episodes="all"), "field episodes is 'all', not list or NoneType"),
                       (lambda m: m.pop("grids"), "of format 3 lacks grids"),
                       (lambda m: m.update(encoder={"width": 8}), "field encoder has no name")):
        broken = _manifest().to_dict()
        edit(broken)
        with pytest.raises(CacheError) as refused:
            Manifest.read(broken, "here", "k")
        assert str(refused.value) == f"here: manifest {says}"


def test_a_manifest_says_trained_by_train_tiny_apart_from_random_init_and_old_ones_read_as_written() -> None:
    """The tower of a policy train-tiny trained records `weights.trained_by`, not random_init; a cache written before
    that field (random_init true for both facts) reads as it was written, and its key is unchanged by the field."""
    from graftcache.extract.provenance import weights_note

    policy = {"source": "policy", "ref": "/p/tiny-smolvla-1", "sha256": "1" * 64, "seed": None}
    trained = manifest(encoder={"name": "smolvla-native", "width": 8}, random_init=False,
                       weights={**policy, "random_init": False, "trained_by": "train-tiny"})
    old = manifest(encoder={"name": "smolvla-native", "width": 8}, random_init=True,
                   weights={**policy, "random_init": True})
    seeded = manifest()
    assert (trained.trained_by, trained.weights_label) == ("train-tiny", "trained by train-tiny")
    assert (old.trained_by, old.weights_label, seeded.weights_label) == (None, "random-init", "random-init")
    assert manifest(random_init=False, weights={"source": "hub"}).weights_label == "hub"
    assert weights_note(trained) == ("note: encoder smolvla-native is the tower of a policy trained by train-tiny "
                                     "(/p/tiny-smolvla-1), not released weights; the manifest says so")
    assert weights_note(old) == ("note: encoder smolvla-native uses RANDOM-INIT weights (policy /p/tiny-smolvla-1); "
                                 "the manifest says so")
    assert weights_note(seeded) == "note: encoder synthetic uses RANDOM-INIT weights (seed 0); the manifest says so"
    assert weights_note(manifest(random_init=False, weights={"source": "hub"})) is None
    assert cache_key(trained.to_dict()) == cache_key(old.to_dict())  # provenance only: the same cache
    assert Manifest.read(trained.to_dict(), "here", "k") == trained
