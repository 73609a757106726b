"""Every dataset failure is one DatasetError line naming the file, episode, frame or key at fault."""

from __future__ import annotations

import json
import re
import shutil
from fractions import Fraction
from pathlib import Path

import av
import pyarrow.parquet as pq
import pytest
from helpers.datasets import FPS, LENGTHS, PI_CAMERAS, V3_CAMERAS, Written, write_v2

from graftcache.datasets import open_dataset
from graftcache.errors import DatasetError


def _copy(written: Written, tmp_path: Path) -> Path:
    return shutil.copytree(written.root, tmp_path / "ds")


def _error(fn, *args) -> str:
    with pytest.raises(DatasetError) as e:
        fn(*args)
    msg = str(e.value)
    assert "\n" not in msg
    return msg


def test_missing_info_json(tmp_path: Path) -> None:
    (tmp_path / "empty").mkdir()
    msg = _error(open_dataset, tmp_path / "empty")
    assert str(tmp_path / "empty" / "meta" / "info.json") in msg and "not a LeRobot dataset" in msg


def test_unknown_codebase_version(v2_pi: Written, tmp_path: Path) -> None:
    root = _copy(v2_pi, tmp_path)
    info = json.loads((root / "meta/info.json").read_text())
    (root / "meta/info.json").write_text(json.dumps({**info, "codebase_version": "v1.6"}))
    msg = _error(open_dataset, root)
    assert str(root / "meta/info.json") in msg and "'v1.6'" in msg and "v2.0, v2.1, v3.0" in msg


def test_missing_camera_lists_available(v2_pi: Written) -> None:
    msg = _error(open_dataset(v2_pi.root).decode_episode, 0, ["image", "agentview"])
    assert "'agentview'" in msg and "image (image)" in msg and "wrist_image (wrist_image)" in msg


def test_unknown_episode(v2_pi: Written) -> None:
    msg = _error(open_dataset(v2_pi.root).decode_episode, 7, ["image"])
    assert "no episode 7" in msg and "0..2" in msg


def _video_of_last_episode(root: Path, key: str) -> tuple[Path, dict]:
    rows = pq.read_table(root / "meta/episodes/chunk-000/file-000.parquet").to_pylist()
    return root / f"videos/{key}/chunk-000/file-000.mp4", rows[-1]


def test_truncated_video_names_file_episode_and_first_missing_frame(v3_video: Written, tmp_path: Path) -> None:
    root = _copy(v3_video, tmp_path)
    path, row = _video_of_last_episode(root, V3_CAMERAS[0])
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * 0.85)])  # lerobot's concatenated mp4s keep the index up front
    ep, start = row["episode_index"], row[f"videos/{V3_CAMERAS[0]}/from_timestamp"]
    survived = 0  # frames of the last episode that still decode, counted independently (no frame delay)
    with av.open(str(path)) as c:
        c.streams.video[0].codec_context.thread_count = 1
        try:
            for f in c.decode(video=0):
                survived += f.time >= start - 0.5 / FPS
        except av.InvalidDataError:
            pass
    assert survived < LENGTHS[ep]
    msg = _error(open_dataset(root).decode_episode, ep, ["image"])
    assert str(path) in msg and f"episode {ep} frame {survived} " in msg
    assert open_dataset(root).decode_episode(0, ["image"])["image"].shape[0] == LENGTHS[0]  # earlier ones still read


def test_unreadable_video_names_file_and_episode(v3_video: Written, tmp_path: Path) -> None:
    root = _copy(v3_video, tmp_path)
    path, _ = _video_of_last_episode(root, V3_CAMERAS[1])
    path.write_bytes(b"not an mp4 at all")
    msg = _error(open_dataset(root).decode_episode, 1, ["image2"])
    assert str(path) in msg and "episode 1 frame 0" in msg


def test_missing_video_file(v3_video: Written, tmp_path: Path) -> None:
    root = _copy(v3_video, tmp_path)
    path, _ = _video_of_last_episode(root, V3_CAMERAS[1])
    path.unlink()
    msg = _error(open_dataset(root).decode_episode, 2, ["image2"])
    assert str(path) in msg and "missing" in msg and "episode 2" in msg


def test_timestamps_outside_video(v3_video: Written, tmp_path: Path) -> None:
    root = _copy(v3_video, tmp_path)
    ep_file = root / "meta/episodes/chunk-000/file-000.parquet"
    table = pq.read_table(ep_file)
    for col, values in (("from_timestamp", [0.0, 0.5, 1.5]), ("to_timestamp", [0.5, 1.2, 2.1])):  # spans = lengths
        col = f"videos/{V3_CAMERAS[0]}/{col}"
        table = table.set_column(table.column_names.index(col), col, [values])
    pq.write_table(table, ep_file)
    path, _ = _video_of_last_episode(root, V3_CAMERAS[0])
    msg = _error(open_dataset(root).decode_episode, 2, ["image"])
    assert str(path) in msg and "episode 2" in msg and "outside the video" in msg
    assert "1.500..2.000 s" in msg and "0..1.700 s" in msg


def test_corrupt_png_names_file_key_episode_frame(v3_image: Written, tmp_path: Path) -> None:
    root = _copy(v3_image, tmp_path)
    data = root / "data/chunk-000/file-000.parquet"
    table = pq.read_table(data)
    col = table.column(V3_CAMERAS[1]).to_pylist()
    col[5 + 3]["bytes"] = col[5 + 3]["bytes"][:40]  # episode 1, frame 3
    table = table.set_column(table.column_names.index(V3_CAMERAS[1]), V3_CAMERAS[1],
                             [col]).cast(table.schema)
    pq.write_table(table, data)
    msg = _error(open_dataset(root).decode_episode, 1, ["image", "image2"])
    assert str(data) in msg and f"{V3_CAMERAS[1]} episode 1 frame 3" in msg


def test_rows_disagreeing_with_metadata(v2_pi: Written, tmp_path: Path) -> None:
    root = _copy(v2_pi, tmp_path)
    lines = (root / "meta/episodes.jsonl").read_text().splitlines()
    lines[1] = json.dumps({**json.loads(lines[1]), "length": 9})
    (root / "meta/episodes.jsonl").write_text("\n".join(lines))
    src = open_dataset(root)
    data = root / "data/chunk-000/episode_000001.parquet"
    assert re.search(re.escape(str(data)) + r": episode 1 has 7 rows, metadata says length 9", _error(src.lowdim))
    assert "episode 1 has 7 rows" in _error(src.decode_episode, 1, PI_CAMERAS)


def test_missing_data_file(v2_pi: Written, tmp_path: Path) -> None:
    root = _copy(v2_pi, tmp_path)
    data = root / "data/chunk-000/episode_000002.parquet"
    data.unlink()
    src = open_dataset(root)
    assert str(data) in _error(src.lowdim, [2])
    msg = _error(src.decode_episode, 2, ["image"])
    assert str(data) in msg and "episode 2" in msg


def test_missing_state_feature(v2_pi: Written, tmp_path: Path) -> None:
    root = _copy(v2_pi, tmp_path)
    info = json.loads((root / "meta/info.json").read_text())
    del info["features"]["state"]
    (root / "meta/info.json").write_text(json.dumps(info))
    msg = _error(open_dataset, root)
    assert "no state feature (looked for observation.state, state)" in msg and "actions" in msg


def test_dropped_frame_is_reported_as_missing(tmp_path: Path) -> None:
    """A recording that skipped a timestamp: the header length is fine, frame 3 simply is not there."""
    written = write_v2(tmp_path / "v21", version="v2.1", video=True)
    path = written.root / f"videos/chunk-000/{PI_CAMERAS[0]}/episode_000001.mp4"
    frames = written.frames[1, PI_CAMERAS[0]]
    with av.open(str(path), "w") as out:
        stream = out.add_stream("libx264", FPS)
        stream.pix_fmt, stream.width, stream.height = "yuv420p", 64, 64
        for t in [0, 1, 2, 4, 5, 6, 7]:
            frame = av.VideoFrame.from_ndarray(frames[min(t, len(frames) - 1)], format="rgb24")
            frame.pts, frame.time_base = t, Fraction(1, FPS)
            out.mux(stream.encode(frame))
        out.mux(stream.encode())
    msg = _error(open_dataset(written.root).decode_episode, 1, [PI_CAMERAS[0]])
    assert str(path) in msg and "short video: episode 1 frame 3 (t=0.300 s) is missing; decoded 6/7 frames" in msg


def test_decode_error_in_a_worker_process_is_one_line(v3_video: Written, tmp_path: Path) -> None:
    """A damaged video met by a decode worker (--num-workers 1): one line naming file and episode, not torch's
    multi-line "Caught DatasetError in DataLoader worker process 0 ... Original Traceback" report."""
    import subprocess
    import sys

    root = _copy(v3_video, tmp_path)
    path, row = _video_of_last_episode(root, V3_CAMERAS[0])
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * 0.85)])
    exe = Path(sys.executable).parent / "graftcache"
    done = subprocess.run([str(exe), "extract", "--encoder", "timm:vit_tiny_patch16_224", "--random-init",
                           "--dataset", str(root), "--num-workers", "1", "--grids", "2x2", "--cache",
                           str(tmp_path / "cache"), "--no-progress"], capture_output=True, text=True, timeout=600)
    lines = done.stderr.strip().splitlines()
    assert done.returncode == 2 and "Traceback" not in done.stderr and "Caught" not in done.stderr, done.stderr
    assert lines[-1].startswith("graftcache extract: error: ") and str(path) in lines[-1]
    assert f"episode {row['episode_index']}" in lines[-1]
    assert not any((tmp_path / "cache").glob("*/zarr.json")) or all(
        not json.loads((p.parent / "zarr.json").read_text())["attributes"].get("complete")
        for p in (tmp_path / "cache").glob("*/zarr.json"))
