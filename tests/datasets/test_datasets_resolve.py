"""Hub repo ids resolve offline through lerobot's home and the hub cache (conftest points both at tmp)."""

from __future__ import annotations

import hashlib
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
from helpers.datasets import LENGTHS, PI_CAMERAS, Written

from graftcache.datasets import open_dataset
from graftcache.errors import DatasetError

REV = "0123456789abcdef0123456789abcdef01234567"


def _hub_snapshot(src: Path, hub: Path, repo_id: str, rev: str = REV) -> Path:
    """The `hf download` layout: blobs by content hash, snapshots/<rev>/ symlinks into them, refs/main."""
    repo = hub / ("datasets--" + repo_id.replace("/", "--"))
    snap = repo / "snapshots" / rev
    for f in sorted(p for p in src.rglob("*") if p.is_file()):
        blob = repo / "blobs" / hashlib.sha256(f.read_bytes()).hexdigest()
        blob.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(f, blob)
        link = snap / f.relative_to(src)
        link.parent.mkdir(parents=True, exist_ok=True)
        link.symlink_to(os.path.relpath(blob, link.parent))
    (repo / "refs").mkdir(exist_ok=True)
    (repo / "refs" / "main").write_text(rev)
    return snap


def _assert_readable(src, written: Written) -> None:
    assert len(src.meta.episodes) == len(LENGTHS)
    np.testing.assert_array_equal(src.decode_episode(1, ["wrist_image"])["wrist_image"],
                                  written.frames[1, PI_CAMERAS[1]])
    assert src.lowdim([0]).height == LENGTHS[0]


def test_hub_cache_snapshot_via_refs_main(v2_pi: Written) -> None:
    snap = _hub_snapshot(v2_pi.root, Path(os.environ["HF_HUB_CACHE"]), "physical-intelligence/libero")
    src = open_dataset("physical-intelligence/libero")
    m = src.meta
    assert (m.root, m.repo_id, m.revision, m.source) == (snap, "physical-intelligence/libero", REV,
                                                           "physical-intelligence/libero")
    assert (snap / "meta/info.json").is_symlink()
    _assert_readable(src, v2_pi)


def test_hub_cache_explicit_revision_and_snapshot_path(v2_pi: Written) -> None:
    snap = _hub_snapshot(v2_pi.root, Path(os.environ["HF_HUB_CACHE"]), "org/pinned", rev="feedbeef")
    (snap.parents[1] / "refs" / "main").unlink()
    assert open_dataset("org/pinned@feedbeef").meta.revision == "feedbeef"
    by_path = open_dataset(snap).meta
    assert (by_path.repo_id, by_path.revision) == ("org/pinned", "feedbeef")
    with pytest.raises(DatasetError, match=r"no refs/main and no snapshot 'main' \(snapshots: feedbeef\)"):
        open_dataset("org/pinned")


def test_hub_cache_default_location_under_hf_home(v2_pi: Written, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("HF_HUB_CACHE")
    monkeypatch.delenv("HF_LEROBOT_HOME")
    _hub_snapshot(v2_pi.root, Path(os.environ["HF_HOME"]) / "hub", "org/default-home")
    assert open_dataset("org/default-home").meta.revision == REV


def test_lerobot_home_wins_over_hub_cache(v2_pi: Written) -> None:
    local = Path(os.environ["HF_LEROBOT_HOME"]) / "org" / "both"
    shutil.copytree(v2_pi.root, local)
    _hub_snapshot(v2_pi.root, Path(os.environ["HF_HUB_CACHE"]), "org/both")
    src = open_dataset("org/both")
    assert (src.meta.root, src.meta.repo_id, src.meta.revision) == (local, "org/both", None)
    _assert_readable(src, v2_pi)


def test_unknown_repo_id_names_where_it_looked() -> None:
    with pytest.raises(DatasetError) as e:
        open_dataset("nobody/nothing")
    msg = str(e.value)
    assert os.path.join(os.environ["HF_LEROBOT_HOME"], "nobody", "nothing") in msg
    assert os.path.join(os.environ["HF_HUB_CACHE"], "datasets--nobody--nothing") in msg
    assert "\n" not in msg


def test_missing_folder_path(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match="no such dataset folder"):
        open_dataset(tmp_path / "does" / "not" / "exist")
