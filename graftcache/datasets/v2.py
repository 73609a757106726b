"""LeRobot v2.0 / v2.1 layout: one parquet (and one mp4 per camera) per episode, JSON-lines metadata.

lerobot 0.4.4 refuses these versions, yet physical-intelligence/libero (v2.0) and many older
LIBERO conversions use them, so graftcache reads them itself. v2.0 and v2.1 differ only in their
stats files (meta/stats.json vs meta/episodes_stats.jsonl), which graftcache does not need.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from graftcache.datasets.layout import EpisodeFiles, Layout, VideoSpan, template_path
from graftcache.datasets.meta import EpisodeMeta
from graftcache.errors import DatasetError

DEFAULT_DATA_PATH = "data/chunk-{episode_chunk:03d}/episode_{episode_index:06d}.parquet"
DEFAULT_VIDEO_PATH = "videos/chunk-{episode_chunk:03d}/{video_key}/episode_{episode_index:06d}.mp4"


def load(root: Path, info: dict[str, Any], video_keys: Sequence[str]) -> Layout:
    """Read tasks.jsonl and episodes.jsonl; per-episode files follow the info.json path templates."""
    tasks_path = root / "meta" / "tasks.jsonl"
    episodes_path = root / "meta" / "episodes.jsonl"
    task_rows = _read_jsonl(tasks_path)
    by_index = {int(r["task_index"]): str(r["task"]) for r in task_rows}
    if sorted(by_index) != list(range(len(by_index))):
        raise DatasetError(f"{tasks_path}: task_index values are not 0..{len(by_index) - 1}")
    tasks = tuple(by_index[i] for i in range(len(by_index)))
    task_index = {t: i for i, t in enumerate(tasks)}

    # lerobot groups episode files in folders of `chunks_size` episodes ({episode_chunk} in the path templates:
    # lerobot's names for its file layout, kept as it writes them); graftcache calls such a folder a file group
    file_group_size = int(info.get("chunks_size", 1000))
    data_tpl = info.get("data_path", DEFAULT_DATA_PATH)
    video_tpl = info.get("video_path") or DEFAULT_VIDEO_PATH
    episodes, files, start = [], [], 0
    for row in sorted(_read_jsonl(episodes_path), key=lambda r: int(r.get("episode_index", -1))):
        if "episode_index" not in row or "length" not in row:
            raise DatasetError(f"{episodes_path}: row {row} lacks episode_index or length")
        ep, length = int(row["episode_index"]), int(row["length"])
        ep_tasks = row.get("tasks") or []
        if not ep_tasks or any(t not in task_index for t in ep_tasks):
            raise DatasetError(f"{episodes_path}: episode {ep} task {ep_tasks!r} is not listed in {tasks_path}")
        if length < 1:
            raise DatasetError(f"{episodes_path}: episode {ep} has length {length}")
        listed = tuple(task_index[t] for t in ep_tasks)
        episodes.append(EpisodeMeta(index=ep, length=length, task_index=listed[0], dataset_from_index=start,
                                    task_indices=listed))
        start += length
        fmt = {"episode_chunk": ep // file_group_size, "episode_index": ep}
        files.append(EpisodeFiles(
            data=template_path(root, "data_path", data_tpl, ep, **fmt),
            videos={key: VideoSpan(template_path(root, "video_path", video_tpl, ep, video_key=key, **fmt), 0.0)
                    for key in video_keys},
        ))
    return Layout(tasks=tasks, episodes=tuple(episodes), files=tuple(files),
                  meta_files=(root / "meta" / "info.json", tasks_path, episodes_path))


def _read_jsonl(path: Path) -> list[dict[str, Any]]:
    if not path.is_file():
        raise DatasetError(f"{path}: missing (v2.x datasets list tasks and episodes there)")
    rows = []
    for n, line in enumerate(path.read_text().splitlines(), start=1):
        if line.strip():
            try:
                rows.append(json.loads(line))
            except json.JSONDecodeError as e:
                raise DatasetError(f"{path}:{n}: not valid JSON ({e.msg})") from None
    return rows
