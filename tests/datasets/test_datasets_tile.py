"""`python -m devtools.tile` (devtools/tile/): bigger datasets made of windows of the bundled sample's frames.

Each tiled episode is checked against the source itself: its frames against an independent PyAV decode of
the source mp4 at the window it points to, its state/action rows against the source rows of the same
frames (in the sample, video frame n of each file is the dataset's row n: asserted, not assumed).
"""

from __future__ import annotations

import json
from collections import Counter
from itertools import pairwise
from pathlib import Path

import av
import numpy as np
import polars as pl
import pyarrow.parquet as pq
import pytest

from devtools.libero_counts import LIBERO_COUNTS
from devtools.tile import TileRequest, tile
from devtools.tile.cli import main
from graftcache.datasets import open_dataset, suite_of
from graftcache.datasets.suites import suite_tasks
from graftcache.errors import GraftcacheError

SAMPLE = Path(__file__).resolve().parents[2] / "data" / "libero_sample"
CAMERAS = ("observation.images.image", "observation.images.image2")


def _episode_rows(root: Path) -> list[dict]:
    return sorted(pq.read_table(root / "meta/episodes/chunk-000/file-000.parquet").to_pylist(),
                  key=lambda r: r["episode_index"])


def _window_starts(root: Path, fps: float) -> dict[str, np.ndarray]:
    """Camera key -> each episode's first frame number in the (single) mp4 it points into."""
    rows = _episode_rows(root)
    for r in rows:
        for key in CAMERAS:
            assert (r[f"videos/{key}/chunk_index"], r[f"videos/{key}/file_index"]) == (0, 0)
            end = r[f"videos/{key}/from_timestamp"] + r["length"] / fps
            assert r[f"videos/{key}/to_timestamp"] == pytest.approx(end)
    return {key: np.array([round(r[f"videos/{key}/from_timestamp"] * fps) for r in rows]) for key in CAMERAS}


@pytest.fixture(scope="module")
def source() -> tuple[pl.DataFrame, float]:
    """The sample's low-dim rows, after checking that its video frame n is its row n."""
    src = open_dataset(SAMPLE)
    for r in _episode_rows(SAMPLE):
        for key in CAMERAS:
            assert round(r[f"videos/{key}/from_timestamp"] * src.meta.fps) == r["dataset_from_index"]
    low = src.lowdim()
    assert low["index"].to_list() == list(range(src.meta.n_frames))
    return low, src.meta.fps


def _assert_rows_follow_windows(root: Path, low: pl.DataFrame, fps: float) -> pl.DataFrame:
    tiled = open_dataset(root).lowdim()
    starts = _window_starts(root, fps)
    np.testing.assert_array_equal(starts[CAMERAS[0]], starts[CAMERAS[1]])
    lengths = tiled.group_by("episode_index", maintain_order=True).len()["len"].to_numpy()
    assert (starts[CAMERAS[0]] >= 0).all() and (starts[CAMERAS[0]] + lengths <= low.height).all()
    rows = np.concatenate([np.arange(s, s + n) for s, n in zip(starts[CAMERAS[0]], lengths)])
    for col in ("state", "action"):
        np.testing.assert_array_equal(tiled[col].to_numpy(), low[col].to_numpy()[rows])
    assert tiled["index"].to_list() == list(range(tiled.height))
    assert tiled["frame_index"].to_list() == [k for n in lengths for k in range(n)]
    np.testing.assert_allclose(tiled["timestamp"].to_numpy(), tiled["frame_index"].to_numpy() / fps, rtol=1e-6)
    return tiled


def test_tiled_episodes_are_source_windows(source, tmp_path: Path) -> None:
    low, fps = source
    dest = tmp_path / "tiled"
    assert main([str(SAMPLE), str(dest), "--episodes", "6", "--frames", "300", "--seed", "3"]) == 0
    tiled = open_dataset(dest)
    meta = tiled.meta
    assert (len(meta.episodes), meta.n_frames) == (6, 300)
    assert meta.tasks == open_dataset(SAMPLE).meta.tasks
    assert [suite_of(meta.tasks[e.task_index]) for e in meta.episodes] == ["libero_spatial"] * 3 + ["libero_object"] * 3
    assert len({e.length for e in meta.episodes}) > 1
    for key in CAMERAS:  # the videos are links to the source's files, not copies
        link = dest / f"videos/{key}/chunk-000/file-000.mp4"
        assert link.is_symlink() and link.resolve() == (SAMPLE / f"videos/{key}/chunk-000/file-000.mp4").resolve()
    _assert_rows_follow_windows(dest, low, fps)

    # pixel-exact on one camera (the other's windows are the same frame numbers of its own linked file, above;
    # the lerobot test below compares both cameras' first and last frames)
    key = CAMERAS[0]
    start = _window_starts(dest, fps)[key]
    wanted = {int(s) + k: (e.index, k) for e, s in zip(meta.episodes, start) for k in range(e.length)}
    reference: dict[tuple[int, int], np.ndarray] = {}
    with av.open(str(SAMPLE / f"videos/{key}/chunk-000/file-000.mp4")) as c:
        for n, frame in enumerate(c.decode(video=0)):
            assert round(frame.time * fps) == n
            if n in wanted:
                reference[wanted[n]] = frame.to_ndarray(format="rgb24")
            if n == max(wanted):
                break
    for e in meta.episodes:
        got = tiled.decode_episode(e.index, [key])[key]
        np.testing.assert_array_equal(got, np.stack([reference[e.index, k] for k in range(e.length)]))


def test_libero_preset_has_lerobot_libero_dimensions(source, tmp_path: Path) -> None:
    low, fps = source
    dest = tile(TileRequest(source=str(SAMPLE), dest=str(tmp_path / "libero"), preset="libero"))
    meta = open_dataset(dest).meta
    assert (len(meta.episodes), meta.n_frames, len(meta.tasks)) == (1693, 273_465, 40)
    suites = [suite_of(meta.tasks[e.task_index]) for e in meta.episodes]
    assert Counter(suites) == {s: n for s, (n, _) in LIBERO_COUNTS.items()}
    frames = Counter()
    for suite, e in zip(suites, meta.episodes):
        frames[suite] += e.length
    assert frames == {s: f for s, (_, f) in LIBERO_COUNTS.items()}
    per_task = Counter(meta.tasks[e.task_index] for e in meta.episodes)
    assert set(per_task) == {t for s in LIBERO_COUNTS for t in suite_tasks()[s]}
    assert max(per_task.values()) - min(per_task.values()) <= 10  # spread evenly within each suite
    info = json.loads((dest / "meta/info.json").read_text())
    assert (info["total_episodes"], info["total_frames"], info["total_tasks"]) == (1693, 273_465, 40)
    assert info["features"] == json.loads((SAMPLE / "meta/info.json").read_text())["features"]
    rows = _episode_rows(dest)
    assert [r["dataset_from_index"] for r in rows] == [e.dataset_from_index for e in meta.episodes]
    assert all(a["dataset_to_index"] == b["dataset_from_index"] for a, b in pairwise(rows))
    tiled = _assert_rows_follow_windows(dest, low, fps)
    stats = json.loads((dest / "meta/stats.json").read_text())
    action = tiled["action"].to_numpy().astype(np.float64)
    assert stats["action"]["count"] == [273_465]
    np.testing.assert_allclose(stats["action"]["mean"], action.mean(axis=0), rtol=1e-6)
    np.testing.assert_allclose(stats["observation.state"]["max"], tiled["state"].to_numpy().max(axis=0))
    assert stats["episode_index"]["max"] == [1692]

    small = {"source": str(SAMPLE), "episodes": 36}  # same seed, same bytes; another seed, other windows
    again = [tile(TileRequest(**small, dest=str(tmp_path / name))) for name in ("a", "b")]
    other = tile(TileRequest(**small, dest=str(tmp_path / "c"), seed=1))
    for name in ("data/chunk-000/file-000.parquet", "meta/episodes/chunk-000/file-000.parquet"):
        assert (again[0] / name).read_bytes() == (again[1] / name).read_bytes()
        assert (other / name).read_bytes() != (again[0] / name).read_bytes()


def test_lerobot_reads_a_tiled_dataset(source, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    monkeypatch.setenv("HF_DATASETS_CACHE", str(tmp_path / "hf_datasets"))
    dest = tile(TileRequest(source=str(SAMPLE), dest=str(tmp_path / "tiled"), episodes=4, frames=200))
    ours = open_dataset(dest)
    low = ours.lowdim()
    ref = LeRobotDataset("local/tiled", root=dest, video_backend="pyav")
    assert (len(ref), ref.num_episodes) == (200, 4)
    for e in ours.meta.episodes:
        frames = ours.decode_episode(e.index, CAMERAS)
        for k in (0, e.length - 1):
            item, row = ref[e.dataset_from_index + k], low.row(e.dataset_from_index + k, named=True)
            assert item["task"] == ours.meta.tasks[e.task_index]
            np.testing.assert_array_equal(item["action"].numpy(), np.asarray(row["action"], np.float32))
            for key in CAMERAS:  # lerobot: float CHW in [0, 1]
                pixels = (item[key].numpy().transpose(1, 2, 0) * 255).round().astype(np.uint8)
                np.testing.assert_array_equal(pixels, frames[key][k])


@pytest.mark.parametrize(("args", "message"), [
    (["--episodes", "1", "--frames", "5000"], "does not fit in the source's longest stretch"),
    (["--episodes", "10", "--frames", "5"], "cannot tile 5 frames into 10 episodes"),
    (["--preset", "nope"], "no tile preset 'nope'; presets: libero"),
    (["--preset", "libero", "--frames", "10"], "frames goes with episodes"),
])
def test_bad_requests_are_one_line_errors(args: list[str], message: str, tmp_path: Path, capsys) -> None:
    assert main([str(SAMPLE), str(tmp_path / "out"), *args]) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and len(err.splitlines()) == 1
    assert list(tmp_path.iterdir()) == []  # nothing half-written


def test_existing_destination_and_non_video_source_are_refused(tmp_path: Path, v2_pi) -> None:
    (tmp_path / "taken").mkdir()
    with pytest.raises(GraftcacheError, match="taken: already exists"):
        tile(TileRequest(source=str(SAMPLE), dest=str(tmp_path / "taken"), episodes=2))
    with pytest.raises(GraftcacheError, match="tile needs a v3.0 dataset whose cameras are all videos"):
        tile(TileRequest(source=str(v2_pi.root), dest=str(tmp_path / "new"), episodes=2))
    with pytest.raises(GraftcacheError, match="exactly one of preset and episodes"):
        TileRequest(source="a", dest="b")
