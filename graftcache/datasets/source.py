"""`open_dataset`: one reader interface over LeRobot v2.0, v2.1 and v3.0, video or PNG storage.

A `LeRobotSource` is metadata plus file locations (no open handles), so it pickles into data-loader
workers in microseconds; each `decode_episode` call opens, decodes and closes its own files.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import polars as pl

from graftcache.datasets import images, v2, v3, video
from graftcache.datasets.layout import EpisodeFiles, Layout
from graftcache.datasets.meta import DatasetMeta, EpisodeMeta, parse_features
from graftcache.datasets.resolve import resolve_source
from graftcache.errors import DatasetError, first_line

#: codebase_version -> reader of that layout.
READERS: dict[str, Callable[[Path, dict[str, Any], Sequence[str]], Layout]] = {
    "v2.0": v2.load,
    "v2.1": v2.load,
    "v3.0": v3.load,
}

#: Low-dim columns copied as they are, with the dtype graftcache stores them in.
INDEX_COLUMNS: dict[str, pl.DataType] = {
    "index": pl.Int64(),
    "episode_index": pl.Int64(),
    "frame_index": pl.Int64(),
    "timestamp": pl.Float32(),
    "task_index": pl.Int64(),
}


def open_dataset(source: str | Path, *, decode_threads: int = 1) -> LeRobotSource:
    """Read a dataset's metadata from a folder or a locally cached hub repo id (see resolve.py).

    `decode_threads`: FFmpeg threads per video decode; 1 suits data workers (one per core), 0 lets
    FFmpeg choose (a single process decoding alone).
    """
    resolved = resolve_source(source)
    root = resolved.root
    info_path = root / "meta" / "info.json"
    if not info_path.is_file():
        raise DatasetError(f"{info_path}: missing; {root} is not a LeRobot dataset")
    try:
        info = json.loads(info_path.read_text())
    except json.JSONDecodeError as e:
        raise DatasetError(f"{info_path}: not valid JSON ({e.msg}, line {e.lineno})") from None
    version = str(info.get("codebase_version"))
    if version not in READERS:
        raise DatasetError(f"{info_path}: codebase_version {version!r} is not supported "
                           f"(supported: {', '.join(READERS)})")
    if "fps" not in info:
        raise DatasetError(f"{info_path}: no fps")
    feats = parse_features(info, info_path)
    video_keys = [feats.camera_keys[c] for c in feats.cameras if feats.camera_storage[c] == "video"]
    layout = READERS[version](root, info, video_keys)
    if not layout.episodes:
        raise DatasetError(f"{root}: the dataset has no episodes (its meta/ folder lists none)")
    meta = DatasetMeta(
        source=str(source),
        root=root,
        repo_id=resolved.repo_id,
        revision=resolved.revision,
        codebase_version=version,
        fps=float(info["fps"]),
        cameras=feats.cameras,
        camera_keys=feats.camera_keys,
        camera_storage=feats.camera_storage,
        image_shape=feats.image_shape,
        state_key=feats.state_key,
        action_key=feats.action_key,
        state_dim=feats.state_dim,
        action_dim=feats.action_dim,
        tasks=layout.tasks,
        episodes=layout.episodes,
        n_frames=sum(e.length for e in layout.episodes),
        identity_files=identity_files(layout, video_keys),
    )
    return LeRobotSource(meta, layout.files, decode_threads=decode_threads)


def identity_files(layout: Layout, video_keys: Sequence[str]) -> tuple[Path, ...]:
    """What a dataset's identity covers: its metadata files, then every data parquet and every mp4 of
    the video cameras that the episodes use (each once, in episode order)."""
    data = [f.data for f in layout.files]
    videos = [f.videos[key].path for key in video_keys for f in layout.files]
    return tuple(dict.fromkeys([*layout.meta_files, *data, *videos]))


class LeRobotSource:
    """Frames and low-dim columns of one dataset, by episode."""

    def __init__(self, meta: DatasetMeta, files: Sequence[EpisodeFiles], *, decode_threads: int = 1) -> None:
        self.meta = meta
        self.decode_threads = decode_threads
        self._files = tuple(files)
        self._position = {e.index: i for i, e in enumerate(meta.episodes)}
        self._short = {key: short for short, key in meta.camera_keys.items()}

    def __repr__(self) -> str:
        m = self.meta
        return (f"LeRobotSource({m.source!r}, {m.codebase_version}, {len(m.episodes)} episodes, "
                f"{m.n_frames} frames, cameras={list(m.cameras)})")

    def decode_episode(self, episode_index: int, cameras: Sequence[str]) -> dict[str, np.ndarray]:
        """Camera (as named in `cameras`: short name or feature key) -> uint8 [T, H, W, 3], T == length."""
        ep, files = self._episode(episode_index)
        shorts = {cam: self._camera(cam) for cam in ([cameras] if isinstance(cameras, str) else cameras)}
        m = self.meta
        png = [s for s in shorts.values() if m.camera_storage[s] == "image"]
        decoded = images.decode_rows(files.data, ep.index, [m.camera_keys[s] for s in png], ep.length,
                                     [m.image_shape[s] for s in png]) if png else {}
        out = {}
        for cam, short in shorts.items():
            key = m.camera_keys[short]
            if key in decoded:
                out[cam] = decoded[key]
            else:
                span = files.videos[key]
                out[cam] = video.decode_span(span.path, span.from_timestamp, ep.length, m.fps, episode=ep.index,
                                             shape=m.image_shape[short], threads=self.decode_threads)
        return out

    def lowdim(self, episodes: Sequence[int] | None = None) -> pl.DataFrame:
        """index, episode_index, frame_index, timestamp, task_index, state, action; dataset order.

        state / action are `Array(Float32, dim)`; only these columns are read, never image bytes.
        """
        m = self.meta
        chosen = [self._episode(e) for e in episodes] if episodes is not None else list(zip(m.episodes, self._files))
        first_episode = {}
        for e, f in chosen:
            first_episode.setdefault(f.data, e.index)
        paths = list(first_episode)
        for p in paths:
            if not p.is_file():
                raise DatasetError(f"{p}: data file missing (episode {first_episode[p]})")
        ids = [e.index for e, _ in chosen]
        frames = [
            pl.scan_parquet(p)
            .filter(pl.col("episode_index").is_in(ids))
            .select(
                *(pl.col(c).cast(t) for c, t in INDEX_COLUMNS.items()),
                pl.col(m.state_key).cast(pl.Array(pl.Float32, m.state_dim)).alias("state"),
                pl.col(m.action_key).cast(pl.Array(pl.Float32, m.action_dim)).alias("action"),
            )
            for p in paths
        ]
        try:
            df = pl.concat(frames).collect().sort("episode_index", "frame_index")
        except pl.exceptions.PolarsError as e:
            raise DatasetError(f"{m.root}: cannot read low-dim columns from {len(paths)} data file(s): "
                               f"{first_line(e)}") from None
        counts = dict(df.group_by("episode_index").len().iter_rows())
        tasks = dict(df.group_by("episode_index").agg(pl.col("task_index").unique().sort()).iter_rows())
        for ep, files in chosen:
            if counts.get(ep.index, 0) != ep.length:
                raise DatasetError(f"{files.data}: episode {ep.index} has "
                                   f"{counts.get(ep.index, 0)} rows, metadata says length {ep.length}")
            stray = sorted(set(tasks[ep.index]) - set(ep.tasks_listed))
            if stray:
                listed = ", ".join(f"{i} ({m.tasks[i]!r})" for i in ep.tasks_listed)
                raise DatasetError(f"{files.data}: episode {ep.index}'s frames have task_index {stray}, "
                                   "which its metadata's tasks list does not name (it lists task_index "
                                   f"{listed})")
        return df

    def _episode(self, episode_index: int) -> tuple[EpisodeMeta, EpisodeFiles]:
        pos = self._position.get(int(episode_index))
        if pos is None:
            ids = [e.index for e in self.meta.episodes]
            raise DatasetError(f"{self.meta.root}: no episode {episode_index} "
                               f"({len(ids)} episodes, indices {min(ids, default=None)}..{max(ids, default=None)})")
        return self.meta.episodes[pos], self._files[pos]

    def _camera(self, camera: str) -> str:
        if camera in self.meta.camera_keys:
            return camera
        if camera in self._short:
            return self._short[camera]
        raise DatasetError(f"{self.meta.root}: no camera {camera!r}; available: "
                           + ", ".join(f"{s} ({k})" for s, k in self.meta.camera_keys.items()))
