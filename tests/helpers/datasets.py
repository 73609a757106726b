"""Real LeRobot datasets on disk for the datasets tests, tiny (64x64, 3 episodes, 18 frames).

The session-wide copies tests take as fixtures (v3_video, v3_video_split, v3_image, v2_pi) are built by
tests/fixtures/datasets.py with these writers.

v3.0 datasets are written by lerobot 0.4.4's own `LeRobotDataset.create` (video or image mode);
v2.0 / v2.1 datasets are written by hand with pyarrow (+ PyAV for mp4) in the layouts of
physical-intelligence/libero (v2.0, PNG in parquet, keys image / wrist_image / state / actions) and of
lerobot's v2.1 video datasets. Every writer returns the arrays it wrote, so tests compare against
the source, not against the reader under test.
"""

from __future__ import annotations

import io
import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import av
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from PIL import Image

from devtools.scheduling import scheduling_kept

H = W = 64
FPS = 10
LENGTHS = (5, 7, 6)
#: Real LIBERO instructions (spatial, object, spatial), so suite mapping can be checked on a dataset.
TASKS = (
    "pick up the black bowl between the plate and the ramekin and place it on the plate",
    "pick up the alphabet soup and place it in the basket",
    "pick up the black bowl between the plate and the ramekin and place it on the plate",
)
V3_CAMERAS = ("observation.images.image", "observation.images.image2")
PI_CAMERAS = ("image", "wrist_image")


@dataclass
class Written:
    """A dataset on disk and what was written into it."""

    root: Path
    repo_id: str
    cameras: tuple[str, ...]  # feature keys
    frames: dict[tuple[int, str], np.ndarray] = field(default_factory=dict)  # (episode, key) -> [T,H,W,3]
    state: dict[int, np.ndarray] = field(default_factory=dict)
    action: dict[int, np.ndarray] = field(default_factory=dict)


def make_frames(episode: int, length: int, camera: int, *, noise: bool) -> np.ndarray:
    """Smooth, distinct-per-frame content (survives lossy codecs); `noise` adds per-pixel detail for PNG."""
    yy, xx = np.mgrid[0:H, 0:W]
    out = np.empty((length, H, W, 3), dtype=np.uint8)
    for t in range(length):
        level = 20 + 60 * episode + 9 * t + 40 * camera
        out[t, ..., 0] = level % 256
        out[t, ..., 1] = (2 * xx + 3 * t) % 256
        out[t, ..., 2] = 255 * (((xx // 8 + t) % 8 < 4) ^ (yy // 16 % 2 == 0))
    if noise:
        rng = np.random.default_rng(1000 * episode + camera)
        out ^= rng.integers(0, 8, size=out.shape, dtype=np.uint8)
    return out


def make_lowdim(episode: int, length: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(episode)
    return (rng.standard_normal((length, 8)).astype(np.float32),
            rng.uniform(-1, 1, (length, 7)).astype(np.float32))


def write_lerobot(root: Path, *, video: bool, vcodec: str = "libsvtav1", small_files: bool = False,
                  repo_id: str = "local/fixture", lengths: tuple[int, ...] = LENGTHS,
                  cameras: tuple[str, ...] = V3_CAMERAS) -> Written:
    """A v3.0 dataset written by lerobot itself (episode i has lengths[i] frames and task TASKS[i]);
    `small_files` forces one data/video file per episode; `cameras` are the camera feature keys."""
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    dtype = "video" if video else "image"
    hwc = {"shape": (H, W, 3), "names": ["height", "width", "channels"]}
    features = {key: {"dtype": dtype, **hwc} for key in cameras}
    features["observation.state"] = {"dtype": "float32", "shape": (8,), "names": None}
    features["action"] = {"dtype": "float32", "shape": (7,), "names": None}
    try:  # lerobot >= 0.5 takes the codec in an encoder config, 0.4 as a keyword
        from lerobot.configs.video import RGBEncoderConfig

        codec = {"rgb_encoder": RGBEncoderConfig(vcodec=vcodec)}
    except ImportError:
        codec = {"vcodec": vcodec}
    ds = LeRobotDataset.create(repo_id=repo_id, fps=FPS, features=features, root=root, robot_type="panda",
                               use_videos=video, **codec)
    if small_files:
        ds.meta.update_chunk_settings(data_files_size_in_mb=0.001, video_files_size_in_mb=0.001)
    written = Written(root=root, repo_id=repo_id, cameras=cameras)
    with scheduling_kept():  # SVT-AV1 as root leaves this thread real-time (devtools/scheduling.py)
        for ep, length in enumerate(lengths):
            for c, key in enumerate(cameras):
                written.frames[ep, key] = make_frames(ep, length, c, noise=not video)
            written.state[ep], written.action[ep] = make_lowdim(ep, length)
            for t in range(length):
                frame = {key: written.frames[ep, key][t] for key in cameras}
                ds.add_frame({**frame, "observation.state": written.state[ep][t], "action": written.action[ep][t],
                              "task": TASKS[ep]})
            ds.save_episode(parallel_encoding=False)
        ds.finalize()
    return written


def write_v2(root: Path, *, version: str = "v2.0", video: bool = False,
             cameras: tuple[str, ...] = PI_CAMERAS, state_key: str = "state", action_key: str = "actions",
             fixed_size_lists: bool = False, row_group_size: int = 3) -> Written:
    """A v2.x dataset by hand: per-episode parquet (+ per-episode mp4 when `video`), JSON-lines metadata."""
    written = Written(root=root, repo_id="local/v2fixture", cameras=cameras)
    (root / "meta").mkdir(parents=True)
    tasks = list(dict.fromkeys(TASKS))
    start = 0
    for ep, length in enumerate(LENGTHS):
        for c, key in enumerate(cameras):
            written.frames[ep, key] = make_frames(ep, length, c, noise=not video)
        written.state[ep], written.action[ep] = make_lowdim(ep, length)
        cols: dict[str, pa.Array] = {}
        for key in cameras:
            if video:
                write_mp4(root / f"videos/chunk-000/{key}/episode_{ep:06d}.mp4", written.frames[ep, key])
            else:
                cols[key] = pa.array([{"bytes": png_bytes(f), "path": f"frame_{t:06d}.png"}
                                      for t, f in enumerate(written.frames[ep, key])],
                                     type=pa.struct([("bytes", pa.binary()), ("path", pa.string())]))
        for key, values in ((state_key, written.state[ep]), (action_key, written.action[ep])):
            list_type = pa.list_(pa.float32(), values.shape[1] if fixed_size_lists else -1)
            cols[key] = pa.array(values.tolist(), type=list_type)
        cols["timestamp"] = pa.array(np.arange(length, dtype=np.float32) / FPS)
        cols["frame_index"] = pa.array(np.arange(length, dtype=np.int64))
        cols["episode_index"] = pa.array(np.full(length, ep, dtype=np.int64))
        cols["index"] = pa.array(np.arange(start, start + length, dtype=np.int64))
        cols["task_index"] = pa.array(np.full(length, tasks.index(TASKS[ep]), dtype=np.int64))
        path = root / f"data/chunk-000/episode_{ep:06d}.parquet"
        path.parent.mkdir(parents=True, exist_ok=True)
        pq.write_table(pa.table(cols), path, row_group_size=row_group_size)
        start += length

    img = {"dtype": "video" if video else "image", "shape": [H, W, 3], "names": ["height", "width", "channel"]}
    features = {key: img for key in cameras}
    features[state_key] = {"dtype": "float32", "shape": [8], "names": [state_key]}
    features[action_key] = {"dtype": "float32", "shape": [7], "names": [action_key]}
    for key, dt in (("timestamp", "float32"), ("frame_index", "int64"), ("episode_index", "int64"),
                    ("index", "int64"), ("task_index", "int64")):
        features[key] = {"dtype": dt, "shape": [1], "names": None}
    info = {
        "codebase_version": version, "robot_type": "panda", "total_episodes": len(LENGTHS),
        "total_frames": sum(LENGTHS), "total_tasks": len(tasks), "total_videos": len(cameras) * len(LENGTHS) * video,
        "total_chunks": 1, "chunks_size": 1000, "fps": FPS, "splits": {"train": f"0:{len(LENGTHS)}"},
        "data_path": "data/chunk-{episode_chunk:03d}/episode_{episode_index:06d}.parquet",
        "video_path": "videos/chunk-{episode_chunk:03d}/{video_key}/episode_{episode_index:06d}.mp4" if video else None,
        "features": features,
    }
    (root / "meta/info.json").write_text(json.dumps(info, indent=4))
    (root / "meta/tasks.jsonl").write_text("".join(json.dumps({"task_index": i, "task": t}) + "\n"
                                                   for i, t in enumerate(tasks)))
    (root / "meta/episodes.jsonl").write_text("".join(
        json.dumps({"episode_index": ep, "tasks": [TASKS[ep]], "length": n}) + "\n" for ep, n in enumerate(LENGTHS)))
    if version == "v2.1":
        (root / "meta/episodes_stats.jsonl").write_text("".join(
            json.dumps({"episode_index": ep, "stats": {}}) + "\n" for ep in range(len(LENGTHS))))
    else:
        (root / "meta/stats.json").write_text("{}")
    return written


def png_bytes(frame: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(frame).save(buf, format="png")
    return buf.getvalue()


def write_mp4(path: Path, frames: np.ndarray, codec: str = "libx264") -> None:
    """An mp4 like lerobot's (yuv420p, keyframe every 2 frames), written with PyAV."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with scheduling_kept(), av.open(str(path), "w") as out:
        stream = out.add_stream(codec, FPS, options={"g": "2", "crf": "23"})
        stream.pix_fmt, stream.width, stream.height = "yuv420p", W, H
        for f in frames:
            out.mux(stream.encode(av.VideoFrame.from_ndarray(f, format="rgb24")))
        out.mux(stream.encode())


def plain_decode(path: Path, from_ts: float, to_ts: float) -> np.ndarray:
    """Independent reference decode: every frame of the file, keep those with from_ts <= t < to_ts."""
    eps = 0.5 / FPS
    with av.open(str(path)) as c:
        frames = [f.to_ndarray(format="rgb24") for f in c.decode(video=0) if from_ts - eps <= f.time < to_ts - eps]
    return np.stack(frames)


def build_lerobot(tmp_path_factory: pytest.TempPathFactory, name: str, **kwargs: object) -> Written:
    """write_lerobot into a fresh temp folder, with lerobot's and datasets' caches kept inside the test temp
    dir (whatever the calling test's environment says)."""
    base = tmp_path_factory.getbasetemp()
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("HF_HOME", str(base / "hf_home"))
        mp.setenv("HF_DATASETS_CACHE", str(base / "hf_home" / "datasets"))
        return write_lerobot(tmp_path_factory.mktemp("ds") / name, **kwargs)


def set_episode_meta(root: Path, episode: int, **values: object) -> Path:
    """Overwrite fields of one episode's metadata row in place (v3.0: its meta/episodes parquet row, whose
    columns are named as lerobot names them, e.g. "tasks", "videos/<key>/to_timestamp"; v2.x: its
    meta/episodes.jsonl line); returns the file edited."""
    jsonl = root / "meta" / "episodes.jsonl"
    if jsonl.is_file():
        rows = [json.loads(line) for line in jsonl.read_text().splitlines() if line.strip()]
        rows = [{**r, **values} if r["episode_index"] == episode else r for r in rows]
        jsonl.write_text("".join(json.dumps(r) + "\n" for r in rows))
        return jsonl
    for path in sorted((root / "meta" / "episodes").rglob("*.parquet")):
        table = pq.read_table(path)
        rows = table.to_pylist()
        if any(r["episode_index"] == episode for r in rows):
            rows = [{**r, **values} if r["episode_index"] == episode else r for r in rows]
            pq.write_table(pa.Table.from_pylist(rows, schema=table.schema), path)
            return path
    raise KeyError(f"{root}: no episode {episode}")


def drop_episodes(root: Path) -> None:
    """Empty a dataset's episode metadata (no episode rows, the files and their columns kept)."""
    jsonl = root / "meta" / "episodes.jsonl"
    if jsonl.is_file():
        jsonl.write_text("")
        return
    for path in (root / "meta" / "episodes").rglob("*.parquet"):
        table = pq.read_table(path)
        pq.write_table(table.slice(0, 0), path)
