"""LeRobot v3.0 layout: episodes in meta/episodes/chunk-XXX/file-YYY.parquet, many episodes per file.

Each episode row names its data file (data/chunk_index, data/file_index: lerobot's names for its file group and
file) and, per camera, its mp4 (videos/<key>/chunk_index, file_index) and where it starts inside it
(from_timestamp).
Task strings live in meta/tasks.parquet (pandas wrote the task as the frame index).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import pyarrow.parquet as pq

from graftcache.datasets.layout import EpisodeFiles, Layout, VideoSpan, template_path
from graftcache.datasets.meta import EpisodeMeta
from graftcache.errors import DatasetError

_TASK_COLUMNS = ("task", "__index_level_0__")


def load(root: Path, info: dict[str, Any], video_keys: Sequence[str]) -> Layout:
    """Read tasks and episode rows; map every episode to its data parquet and video spans."""
    tasks_path = root / "meta" / "tasks.parquet"
    tasks = _read_tasks(tasks_path)
    task_index = {t: i for i, t in enumerate(tasks)}
    ep_files = sorted((root / "meta" / "episodes").glob("chunk-*/file-*.parquet"))
    if not ep_files:
        raise DatasetError(f"{root / 'meta' / 'episodes'}: no chunk-*/file-*.parquet episode metadata")
    columns = ["episode_index", "tasks", "length", "data/chunk_index", "data/file_index", "dataset_from_index"]
    for key in video_keys:
        columns += [f"videos/{key}/chunk_index", f"videos/{key}/file_index", f"videos/{key}/from_timestamp"]
    rows = sorted(((f, row) for f in ep_files for row in _read_rows(f, columns)),
                  key=lambda file_row: file_row[1]["episode_index"])

    episodes, files = [], []
    for ep_file, row in rows:
        ep = int(row["episode_index"])
        _check_extent(row, ep_file, float(info["fps"]), video_keys)
        tasks_of = _tasks_of(row["tasks"], task_index, ep, tasks_path)
        episodes.append(EpisodeMeta(index=ep, length=int(row["length"]), task_index=tasks_of[0],
                                    dataset_from_index=int(row["dataset_from_index"]), task_indices=tasks_of))
        data = template_path(root, "data_path", info.get("data_path"), ep, chunk_index=int(row["data/chunk_index"]),
                             file_index=int(row["data/file_index"]))
        videos = {
            key: VideoSpan(
                path=template_path(root, "video_path", info.get("video_path"), ep, video_key=key,
                                   chunk_index=int(row[f"videos/{key}/chunk_index"]),
                                   file_index=int(row[f"videos/{key}/file_index"])),
                from_timestamp=float(row[f"videos/{key}/from_timestamp"]),
            )
            for key in video_keys
        }
        files.append(EpisodeFiles(data=data, videos=videos))
    return Layout(tasks=tasks, episodes=tuple(episodes), files=tuple(files),
                  meta_files=(root / "meta" / "info.json", tasks_path, *ep_files))


def _read_tasks(path: Path) -> tuple[str, ...]:
    if not path.is_file():
        raise DatasetError(f"{path}: missing (v3.0 datasets list their task strings there)")
    table = pq.read_table(path)
    name = next((c for c in _TASK_COLUMNS if c in table.column_names), None)
    if name is None or "task_index" not in table.column_names:
        raise DatasetError(f"{path}: expected columns task_index and task, found {', '.join(table.column_names)}")
    by_index = dict(zip(table.column("task_index").to_pylist(), table.column(name).to_pylist()))
    if sorted(by_index) != list(range(len(by_index))):
        raise DatasetError(f"{path}: task_index values are not 0..{len(by_index) - 1}")
    return tuple(by_index[i] for i in range(len(by_index)))


def _read_rows(path: Path, columns: list[str]) -> list[dict[str, Any]]:
    """The episode rows of one metadata file: `columns`, and the optional ones restating its extent."""
    names = pq.read_schema(path).names
    missing = [c for c in columns if c not in names]
    if missing:
        raise DatasetError(f"{path}: missing episode column(s) {', '.join(missing)}")
    optional = [c for c in names
                if c == "dataset_to_index" or (c.startswith("videos/") and c.endswith("/to_timestamp"))]
    return pq.read_table(path, columns=columns + optional).to_pylist()


def _tasks_of(episode_tasks: list[str] | None, task_index: dict[str, int], episode: int,
              tasks_path: Path) -> tuple[int, ...]:
    """The task_index of every task the episode row lists, its first task first (LIBERO episodes have one)."""
    if not episode_tasks or any(t not in task_index for t in episode_tasks):
        raise DatasetError(f"episode {episode}: task {episode_tasks!r} is not listed in {tasks_path}")
    return tuple(task_index[t] for t in episode_tasks)


#: How far (in frames) a camera's from..to_timestamp span may be from `length`: a whole frame contradicts it.
_EXTENT_FRAMES = 1.0


def _check_extent(row: dict[str, Any], path: Path, fps: float, video_keys: Sequence[str]) -> None:
    """An episode row whose own columns disagree on its length is refused: `dataset_to_index` -
    `dataset_from_index`, and per camera `to_timestamp` - `from_timestamp` times fps, must give `length`
    (the timestamps to within less than a frame). Reading on would decode the wrong span of a video or
    pair features with the rows of another episode."""
    ep, length = int(row["episode_index"]), int(row["length"])
    if length < 1:
        raise DatasetError(f"{path}: episode {ep} has length {length}")
    end = row.get("dataset_to_index")
    if end is not None and int(end) - int(row["dataset_from_index"]) != length:
        raise DatasetError(f"{path}: episode {ep} spans dataset rows {row['dataset_from_index']}..{end} "
                           f"({int(end) - int(row['dataset_from_index'])} rows), but its length is {length}")
    for key in video_keys:
        start, stop = row[f"videos/{key}/from_timestamp"], row.get(f"videos/{key}/to_timestamp")
        frames = None if stop is None else (float(stop) - float(start)) * fps
        if frames is not None and abs(frames - length) >= _EXTENT_FRAMES:
            raise DatasetError(f"{path}: episode {ep} camera {key}: from_timestamp {start:.3f} s to "
                               f"to_timestamp {stop:.3f} s is {frames:.1f} frames at {fps:g} fps, but its "
                               f"length is {length} frames")
