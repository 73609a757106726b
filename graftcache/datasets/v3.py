"""LeRobot v3.0 layout: episodes in meta/episodes/chunk-XXX/file-YYY.parquet, many episodes per file.

Each episode row names its data file (data/chunk_index, data/file_index) and, per camera, its mp4
(videos/<key>/chunk_index, file_index) and where it starts inside it (from_timestamp).
Task strings live in meta/tasks.parquet (pandas wrote the task as the frame index).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Sequence

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
    rows = sorted((row for f in ep_files for row in _read_rows(f, columns)), key=lambda r: r["episode_index"])

    episodes, files = [], []
    for row in rows:
        ep = int(row["episode_index"])
        episodes.append(EpisodeMeta(index=ep, length=int(row["length"]),
                                    task_index=_task_of(row["tasks"], task_index, ep, tasks_path),
                                    dataset_from_index=int(row["dataset_from_index"])))
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
    names = pq.read_schema(path).names
    missing = [c for c in columns if c not in names]
    if missing:
        raise DatasetError(f"{path}: missing episode column(s) {', '.join(missing)}")
    return pq.read_table(path, columns=columns).to_pylist()


def _task_of(episode_tasks: list[str] | None, task_index: dict[str, int], episode: int, tasks_path: Path) -> int:
    """The episode's first task; LIBERO episodes have exactly one."""
    if not episode_tasks or episode_tasks[0] not in task_index:
        raise DatasetError(f"episode {episode}: task {episode_tasks!r} is not listed in {tasks_path}")
    return task_index[episode_tasks[0]]
