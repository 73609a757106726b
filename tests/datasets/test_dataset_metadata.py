"""Episode metadata that contradicts the data is refused in one line naming the file and the episode, before
any cache exists: a from..to_timestamp span or a dataset_to_index that disagrees with the episode's length, a
`tasks` list that the frames' task_index contradicts, and a dataset that lists no episode at all."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
from helpers.datasets import FPS, LENGTHS, TASKS, V3_CAMERAS, Written, drop_episodes, set_episode_meta

from graftcache.cli import main
from graftcache.datasets import open_dataset
from graftcache.errors import DatasetError

EXTRACT = ["extract", "--encoder", "timm:vit_tiny_patch16_224", "--random-init", "--grids", "2x2",
           "--num-workers", "0", "--no-progress"]


def _copy(written: Written, tmp_path: Path) -> Path:
    return shutil.copytree(written.root, tmp_path / "ds")


def _refused(root: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> str:
    """`extract` of `root` fails with one line and leaves no cache behind; returns that line."""
    cache = tmp_path / "cache"
    assert main([*EXTRACT, "--dataset", str(root), "--cache", str(cache)]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    assert not cache.exists() or not any(cache.iterdir())
    return err.strip()


def test_to_timestamp_that_disagrees_with_the_length(v3_video: Written, tmp_path: Path,
                                                     capsys: pytest.CaptureFixture) -> None:
    root = _copy(v3_video, tmp_path)
    key = V3_CAMERAS[1]
    start = 0.5  # episode 1 starts 0.5 s into the shared mp4 (episode 0 has LENGTHS[0] = 5 frames at 10 fps)
    stop = start + (LENGTHS[1] - 2) / FPS  # two frames short of its 7
    path = set_episode_meta(root, 1, **{f"videos/{key}/to_timestamp": stop})
    with pytest.raises(DatasetError) as e:
        open_dataset(root)
    assert str(e.value) == (f"{path}: episode 1 camera {key}: from_timestamp {start:.3f} s "
                            f"to to_timestamp {stop:.3f} s "
                            f"is {LENGTHS[1] - 2:.1f} frames at {FPS} fps, but its length is {LENGTHS[1]} frames")
    assert _refused(root, tmp_path, capsys).endswith(str(e.value))


def test_a_span_within_a_frame_of_the_length_is_accepted(v3_video: Written, tmp_path: Path) -> None:
    """Real datasets' to_timestamp comes from the encoded video's duration, a fraction of a frame off."""
    root = _copy(v3_video, tmp_path)
    set_episode_meta(root, 1, **{f"videos/{V3_CAMERAS[0]}/to_timestamp": 0.5 + (LENGTHS[1] + 0.9) / FPS})
    assert [e.length for e in open_dataset(root).meta.episodes] == list(LENGTHS)


def test_dataset_to_index_that_disagrees_with_the_length(v3_video: Written, tmp_path: Path) -> None:
    root = _copy(v3_video, tmp_path)
    path = set_episode_meta(root, 2, dataset_to_index=sum(LENGTHS) + 3)
    with pytest.raises(DatasetError) as e:
        open_dataset(root)
    first = LENGTHS[0] + LENGTHS[1]
    assert str(e.value) == (f"{path}: episode 2 spans dataset rows {first}..{sum(LENGTHS) + 3} "
                            f"({LENGTHS[2] + 3} rows), but its length is {LENGTHS[2]}")


@pytest.mark.parametrize("layout", ["v3", "v2"])
def test_tasks_list_that_contradicts_the_frames_task_index(layout: str, v3_image: Written, v2_pi: Written,
                                                           tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """Episode 1's metadata names episode 0's task; its frames keep task_index 1 (the alphabet soup)."""
    root = _copy(v3_image if layout == "v3" else v2_pi, tmp_path)
    set_episode_meta(root, 1, tasks=[TASKS[0]])
    source = open_dataset(root)  # the metadata alone is consistent: the contradiction is with the frames
    assert source.meta.episodes[1].task_index == 0
    data = next(p for p in sorted((root / "data").rglob("*.parquet")) if layout == "v3" or "000001" in p.name)
    with pytest.raises(DatasetError) as e:
        source.lowdim()
    assert str(e.value) == (f"{data}: episode 1's frames have task_index [1], which its metadata's tasks list does "
                            f"not name (it lists task_index 0 ({TASKS[0]!r}))")
    assert _refused(root, tmp_path, capsys).endswith(str(e.value))
    assert source.lowdim([0, 2]).height == LENGTHS[0] + LENGTHS[2]  # the consistent episodes still read


@pytest.mark.parametrize("layout", ["v3", "v2"])
def test_a_dataset_with_no_episodes(layout: str, v3_image: Written, v2_pi: Written, tmp_path: Path,
                                    capsys: pytest.CaptureFixture) -> None:
    root = _copy(v3_image if layout == "v3" else v2_pi, tmp_path)
    drop_episodes(root)
    with pytest.raises(DatasetError) as e:
        open_dataset(root)
    assert str(e.value) == f"{root}: the dataset has no episodes (its meta/ folder lists none)"
    assert _refused(root, tmp_path, capsys).endswith(str(e.value))
