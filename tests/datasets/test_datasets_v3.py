"""v3.0 datasets written by lerobot 0.4.4 itself are read frame-exactly and agree with LeRobotDataset."""

from __future__ import annotations

import hashlib
import pickle
import shutil
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
import torch
from helpers.datasets import FPS, LENGTHS, TASKS, V3_CAMERAS, Written, plain_decode, write_lerobot

from graftcache.datasets import open_dataset
from graftcache.runtime import single_thread_worker


def _episode_rows(root: Path) -> list[dict]:
    """Episode metadata read straight from the parquet, independent of the reader under test."""
    files = sorted((root / "meta/episodes").rglob("*.parquet"))
    return sorted((r for f in files for r in pq.read_table(f).to_pylist()), key=lambda r: r["episode_index"])


def _assert_video_exact(written: Written) -> None:
    src = open_dataset(written.root)
    for row in _episode_rows(written.root):
        ep = row["episode_index"]
        got = src.decode_episode(ep, V3_CAMERAS)
        for key in V3_CAMERAS:
            path = written.root / f"videos/{key}/chunk-{row[f'videos/{key}/chunk_index']:03d}/" \
                                  f"file-{row[f'videos/{key}/file_index']:03d}.mp4"
            ref = plain_decode(path, row[f"videos/{key}/from_timestamp"], row[f"videos/{key}/to_timestamp"])
            assert got[key].shape == ref.shape == (LENGTHS[ep], 64, 64, 3)
            np.testing.assert_array_equal(got[key], ref)
            # and each decoded frame is closest to the source frame it was encoded from
            source = written.frames[ep, key].astype(np.float32)
            err = np.abs(got[key][:, None].astype(np.float32) - source[None]).mean(axis=(2, 3, 4))
            assert (err.argmin(axis=1) == np.arange(LENGTHS[ep])).all()
            assert err.diagonal().max() < 8


@pytest.mark.parametrize("name", ["v3_video", "v3_video_split"])
def test_video_frames_equal_independent_pyav_decode(name: str, request: pytest.FixtureRequest) -> None:
    written = request.getfixturevalue(name)
    if name == "v3_video_split":  # the fixture really spreads episodes over several files
        assert len(list((written.root / "videos" / V3_CAMERAS[0]).rglob("*.mp4"))) == len(LENGTHS)
        assert len(list((written.root / "data").rglob("*.parquet"))) == len(LENGTHS)
    _assert_video_exact(written)


@pytest.mark.parametrize("vcodec", ["h264", "hevc"])
def test_other_lerobot_codecs(vcodec: str, tmp_path: Path) -> None:
    _assert_video_exact(write_lerobot(tmp_path / vcodec, video=True, vcodec=vcodec))


def test_image_mode_is_bit_exact(v3_image: Written) -> None:
    src = open_dataset(v3_image.root)
    assert src.meta.camera_storage == {"image": "image", "image2": "image"}
    for ep in range(len(LENGTHS)):
        got = src.decode_episode(ep, ["image", "image2"])
        np.testing.assert_array_equal(got["image"], v3_image.frames[ep, V3_CAMERAS[0]])
        np.testing.assert_array_equal(got["image2"], v3_image.frames[ep, V3_CAMERAS[1]])


def test_image_rows_spanning_row_groups(v3_image: Written, tmp_path: Path) -> None:
    """Episodes that start and end mid row group are still cut exactly."""
    root = shutil.copytree(v3_image.root, tmp_path / "ds")
    data = root / "data/chunk-000/file-000.parquet"
    pq.write_table(pq.read_table(data), data, row_group_size=4)
    assert pq.ParquetFile(data).metadata.num_row_groups == 5
    src = open_dataset(root)
    for ep in range(len(LENGTHS)):
        np.testing.assert_array_equal(src.decode_episode(ep, ["image2"])["image2"], v3_image.frames[ep, V3_CAMERAS[1]])


def test_meta(v3_video: Written) -> None:
    m = open_dataset(v3_video.root).meta
    assert (m.codebase_version, m.fps, m.repo_id, m.revision) == ("v3.0", FPS, None, None)
    assert m.root == v3_video.root.resolve() and m.source == str(v3_video.root)
    assert m.cameras == ("image", "image2")
    assert m.camera_keys == {"image": V3_CAMERAS[0], "image2": V3_CAMERAS[1]}
    assert m.camera_storage == {"image": "video", "image2": "video"}
    assert m.image_shape == {"image": (64, 64, 3), "image2": (64, 64, 3)}
    assert (m.state_key, m.state_dim, m.action_key, m.action_dim) == ("observation.state", 8, "action", 7)
    assert m.tasks == (TASKS[0], TASKS[1])
    assert [(e.index, e.length, e.task_index, e.dataset_from_index) for e in m.episodes] == [
        (0, 5, 0, 0), (1, 7, 1, 5), (2, 6, 0, 12)]
    assert m.n_frames == sum(LENGTHS)
    files = m.content_identity["files"]
    assert set(files) == {"meta/info.json", "meta/tasks.parquet", "meta/episodes/chunk-000/file-000.parquet",
                          "data/chunk-000/file-000.parquet",
                          *(f"videos/{k}/chunk-000/file-000.mp4" for k in V3_CAMERAS)}
    for rel, entry in files.items():
        data = (v3_video.root / rel).read_bytes()
        assert entry == {"size": len(data), "sha256": hashlib.sha256(data).hexdigest()}, rel


@pytest.mark.parametrize("name", ["v3_video", "v3_image"])
def test_agrees_with_lerobot_dataset(name: str, request: pytest.FixtureRequest) -> None:
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    written = request.getfixturevalue(name)
    src = open_dataset(written.root)
    low = src.lowdim()
    frames = {ep: src.decode_episode(ep, V3_CAMERAS) for ep in range(len(LENGTHS))}
    ref = LeRobotDataset(written.repo_id, root=written.root, video_backend="pyav")
    assert len(ref) == low.height == src.meta.n_frames
    for i in range(len(ref)):
        item, row = ref[i], low.row(i, named=True)
        for col in ("index", "episode_index", "frame_index", "task_index"):
            assert int(item[col]) == row[col], (i, col)
        assert float(item["timestamp"]) == row["timestamp"]
        np.testing.assert_array_equal(item["observation.state"].numpy(), np.asarray(row["state"], np.float32))
        np.testing.assert_array_equal(item["action"].numpy(), np.asarray(row["action"], np.float32))
        assert item["task"] == src.meta.tasks[row["task_index"]]
        for key in V3_CAMERAS:  # lerobot: float CHW in [0, 1]
            ours = frames[row["episode_index"]][key][row["frame_index"]]
            theirs = (item[key].permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)
            np.testing.assert_array_equal(ours, theirs)


def test_lowdim_subset_equals_source(v3_video_split: Written) -> None:
    src = open_dataset(v3_video_split.root)
    low = src.lowdim([2, 0])
    assert low.columns == ["index", "episode_index", "frame_index", "timestamp", "task_index", "state", "action"]
    assert low["episode_index"].to_list() == [0] * LENGTHS[0] + [2] * LENGTHS[2]
    assert low["index"].to_list() == list(range(0, 5)) + list(range(12, 18))
    assert low["frame_index"].to_list() == list(range(5)) + list(range(6))
    np.testing.assert_allclose(low["timestamp"].to_numpy(), np.r_[np.arange(5), np.arange(6)] / FPS, rtol=1e-6)
    assert low["task_index"].to_list() == [0] * 11
    for column in ("state", "action"):
        kept = getattr(v3_video_split, column)
        np.testing.assert_array_equal(low[column].to_numpy(), np.concatenate([kept[0], kept[2]]))


def test_camera_by_key_or_short_name(v3_video: Written) -> None:
    src = open_dataset(v3_video.root)
    by_key = src.decode_episode(1, [V3_CAMERAS[1]])
    by_short = src.decode_episode(1, ["image2"])
    assert list(by_key) == [V3_CAMERAS[1]] and list(by_short) == ["image2"]
    np.testing.assert_array_equal(by_key[V3_CAMERAS[1]], by_short["image2"])


class _Episodes(torch.utils.data.Dataset):
    def __init__(self, src) -> None:
        self.src = src

    def __len__(self) -> int:
        return len(self.src.meta.episodes)

    def __getitem__(self, i: int) -> dict[str, np.ndarray]:
        return self.src.decode_episode(self.src.meta.episodes[i].index, self.src.meta.cameras)


def test_source_pickles_and_decodes_in_workers(v3_video_split: Written) -> None:
    src = open_dataset(v3_video_split.root)
    clone = pickle.loads(pickle.dumps(src))
    assert clone.meta == src.meta
    expected = [src.decode_episode(e, src.meta.cameras) for e in range(len(LENGTHS))]
    np.testing.assert_array_equal(clone.decode_episode(2, ["image"])["image"], expected[2]["image"])
    loader = torch.utils.data.DataLoader(_Episodes(clone), batch_size=None, num_workers=2,
                                         worker_init_fn=single_thread_worker)
    for got, exp in zip(loader, expected, strict=True):
        for cam in src.meta.cameras:
            np.testing.assert_array_equal(got[cam].numpy(), exp[cam])
