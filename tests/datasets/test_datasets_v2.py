"""v2.0 (physical-intelligence/libero layout) and v2.1 (per-episode mp4) datasets, written by hand, read exactly."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import polars as pl
from helpers.datasets import FPS, LENGTHS, PI_CAMERAS, TASKS, Written, plain_decode, write_v2

from graftcache.datasets import open_dataset

V21_CAMERAS = ("observation.images.image", "observation.images.wrist_image")


def _assert_lowdim(low: pl.DataFrame, written: Written) -> None:
    assert low.schema["state"] == pl.Array(pl.Float32, 8) and low.schema["action"] == pl.Array(pl.Float32, 7)
    assert low["index"].to_list() == list(range(sum(LENGTHS)))
    assert low["episode_index"].to_list() == [e for e, n in enumerate(LENGTHS) for _ in range(n)]
    assert low["frame_index"].to_list() == [t for n in LENGTHS for t in range(n)]
    assert low["task_index"].to_list() == [0] * 5 + [1] * 7 + [0] * 6
    np.testing.assert_allclose(low["timestamp"].to_numpy(), np.concatenate([np.arange(n) / FPS for n in LENGTHS]),
                               rtol=1e-6)
    np.testing.assert_array_equal(low["state"].to_numpy(), np.concatenate([written.state[e] for e in range(3)]))
    np.testing.assert_array_equal(low["action"].to_numpy(), np.concatenate([written.action[e] for e in range(3)]))


def test_v20_pi_layout_meta(v2_pi: Written) -> None:
    m = open_dataset(v2_pi.root).meta
    assert m.codebase_version == "v2.0" and m.fps == FPS
    assert m.cameras == PI_CAMERAS and m.camera_keys == {c: c for c in PI_CAMERAS}
    assert m.camera_storage == {c: "image" for c in PI_CAMERAS}
    assert (m.state_key, m.state_dim, m.action_key, m.action_dim) == ("state", 8, "actions", 7)
    assert m.tasks == (TASKS[0], TASKS[1])
    assert [(e.index, e.length, e.task_index, e.dataset_from_index) for e in m.episodes] == [
        (0, 5, 0, 0), (1, 7, 1, 5), (2, 6, 0, 12)]
    # the identity covers the metadata and every data file (PNG frames live in the per-episode parquets)
    assert list(m.content_identity["files"]) == ["meta/info.json", "meta/tasks.jsonl", "meta/episodes.jsonl",
                                            *(f"data/chunk-000/episode_{e:06d}.parquet" for e in range(3))]


def test_v20_pi_layout_frames_bit_exact_and_lowdim(v2_pi: Written) -> None:
    src = open_dataset(v2_pi.root)
    for ep in range(len(LENGTHS)):
        got = src.decode_episode(ep, PI_CAMERAS)
        for cam in PI_CAMERAS:
            np.testing.assert_array_equal(got[cam], v2_pi.frames[ep, cam])
    _assert_lowdim(src.lowdim(), v2_pi)


def test_v21_video_variant(tmp_path: Path) -> None:
    written = write_v2(tmp_path / "v21", version="v2.1", video=True, cameras=V21_CAMERAS,
                       state_key="observation.state", action_key="action", fixed_size_lists=True)
    src = open_dataset(written.root)
    m = src.meta
    assert m.codebase_version == "v2.1" and m.cameras == ("image", "wrist_image")
    assert m.camera_storage == {"image": "video", "wrist_image": "video"}
    for ep, n in enumerate(LENGTHS):
        got = src.decode_episode(ep, m.cameras)
        for cam, key in m.camera_keys.items():
            ref = plain_decode(written.root / f"videos/chunk-000/{key}/episode_{ep:06d}.mp4", 0.0, n / FPS)
            np.testing.assert_array_equal(got[cam], ref)
            assert np.abs(got[cam].astype(int) - written.frames[ep, key]).mean() < 4
    _assert_lowdim(src.lowdim(), written)
