"""Files graftcache writes into shared places take their mode from the user's umask, never 0600 (issue 15).

safetensors >= 0.8 creates its output through a 0600 temporary file; `follow_umask` gives such files
the mode an ordinary write would have had. Caches (zarr + markers), results and the hash sidecar are
written with plain file writes and must already follow the umask.
"""

from __future__ import annotations

import os
import stat
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import polars as pl
import pytest
import torch
from helpers.caches import manifest

from graftcache.store import cache_key
from graftcache.store.cache import ArraySpec, FeatureCache, to_storage


@contextmanager
def umask(mask: int) -> Iterator[None]:
    old = os.umask(mask)
    try:
        yield
    finally:
        os.umask(old)


def _modes(root: Path) -> dict[str, set[int]]:
    out: dict[str, set[int]] = {"file": set(), "dir": set()}
    for p in [root, *root.rglob("*")]:
        out["dir" if p.is_dir() else "file"].add(stat.S_IMODE(p.stat().st_mode))
    return out


@pytest.mark.parametrize("mask", [0o022, 0o027, 0o002])
def test_safetensors_files_follow_the_umask(tmp_path: Path, mask: int) -> None:
    from safetensors.torch import save_file

    from graftcache.backbones.checkpoint import current_umask, follow_umask

    with umask(mask):
        assert current_umask() == mask
        folder = tmp_path / "policy"
        folder.mkdir()
        save_file({"w": torch.zeros(3)}, str(folder / "model.safetensors"))
        (folder / "config.json").write_text("{}")
        follow_umask(folder)
        save_file({"w": torch.zeros(3)}, str(tmp_path / "projector.safetensors"))
        follow_umask(tmp_path / "projector.safetensors")
    want = 0o666 & ~mask
    assert _modes(folder)["file"] == {want}
    assert stat.S_IMODE((tmp_path / "projector.safetensors").stat().st_mode) == want


@pytest.mark.parametrize("mask", [0o022, 0o027])
def test_cache_files_follow_the_umask(tmp_path: Path, mask: int) -> None:
    n = 10
    index = pl.DataFrame({"index": np.arange(n), "episode_index": np.zeros(n, int), "frame_index": np.arange(n),
                          "task_index": np.zeros(n, int), "suite_index": np.zeros(n, int),
                          "timestamp": np.arange(n) / 10.0, "state": np.zeros((n, 2), np.float32).tolist(),
                          "action": np.zeros((n, 2), np.float32).tolist()})
    made = manifest(cameras=["image"], grids=["1x1"], n_frames=n)
    with umask(mask):
        cache = FeatureCache.create(tmp_path / cache_key(made.to_dict()), made,
                                    [ArraySpec("features/image/1x1", (1, 4))], index, block_frames=4)
        for b in range(cache.layout["n_blocks"]):
            s, e = cache.block_range(b)
            cache.write_block(b, {"features/image/1x1": to_storage(torch.ones(e - s, 1, 4), "fp16")})
        cache.finalize()
    modes = _modes(tmp_path / cache_key(made.to_dict()))
    assert modes["file"] == {0o666 & ~mask} and modes["dir"] == {0o777 & ~mask}


def test_hash_sidecar_follows_the_umask(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from graftcache.datasets import identity

    monkeypatch.setenv(identity.MEMO_ENV, str(tmp_path / "memo"))
    (tmp_path / "f").write_bytes(b"x")
    with umask(0o022):
        identity.content_identity(tmp_path, [tmp_path / "f"])
    (sidecar,) = (tmp_path / "memo").iterdir()
    assert stat.S_IMODE(sidecar.stat().st_mode) == 0o644


def test_an_unreadable_checkpoint_file_is_one_clear_error(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Checkpoints saved 0600 by an older graftcache: name the file and the fix, not a FileNotFoundError."""
    from graftcache.backbones import checkpoint
    from graftcache.errors import BackboneError

    folder = tmp_path / "tiny-smolvla-abc"
    folder.mkdir()
    (folder / "config.json").write_text("{}")
    (folder / "model.safetensors").write_bytes(b"x")
    assert checkpoint.resolve_source(folder) == folder
    real_access = os.access
    monkeypatch.setattr(checkpoint.os, "access",  # as root every file is readable: stand in for another user
                        lambda p, mode: Path(p).name != "model.safetensors" and real_access(p, mode))
    with pytest.raises(BackboneError, match=r"model.safetensors: not readable by this user .*chmod -R go\+rX") as err:
        checkpoint.resolve_source(folder)
    assert len(str(err.value).splitlines()) == 1


def test_saved_policies_and_projectors_follow_the_umask(tmp_path: Path) -> None:
    """safetensors writes 0600 files; graftcache's saves must leave them readable under umask 022."""
    from helpers.backbones import tiny

    previous = os.umask(0o022)
    try:
        folder = tiny("smolvla").save(tmp_path / "policy")
    finally:
        os.umask(previous)
    modes = {p.name: stat.S_IMODE(p.stat().st_mode) for p in folder.rglob("*") if p.is_file()}
    assert modes and all(mode == 0o644 for mode in modes.values()), modes
