"""Where each episode's bytes live on disk: the output of a version reader (v2.py, v3.py).

Plain frozen dataclasses of paths and numbers, so a `LeRobotSource` pickles cheaply into data-loader
workers and no file handle crosses a process boundary.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from graftcache.datasets.meta import EpisodeMeta
from graftcache.errors import DatasetError


@dataclass(frozen=True)
class VideoSpan:
    """One episode of one camera inside an mp4 that may hold several episodes back to back."""

    path: Path
    from_timestamp: float  # seconds into the file where the episode's frame 0 is


@dataclass(frozen=True)
class EpisodeFiles:
    """The parquet file holding an episode's rows, and its video span per camera feature key."""

    data: Path
    videos: dict[str, VideoSpan]


@dataclass(frozen=True)
class Layout:
    """A version reader's answer: tasks, episodes (ascending), their files, and the files its identity hashes."""

    tasks: tuple[str, ...]
    episodes: tuple[EpisodeMeta, ...]
    files: tuple[EpisodeFiles, ...]  # aligned with `episodes`
    meta_files: tuple[Path, ...]


def template_path(root: Path, key: str, template: Any, episode: int, **fields: Any) -> Path:
    """`root / template.format(**fields)` for the meta/info.json path template `key` (data_path, video_path),
    which must name a file inside `root`: a template (or a camera key) with `..` or an absolute path would
    make extraction read files outside the dataset. The check is on the normalised path, not on symlink
    targets, because a hub-cache snapshot's files are symlinks into the repo's blobs folder."""
    where = root / "meta" / "info.json"
    if not isinstance(template, str) or not template:
        raise DatasetError(f"{where}: {key} is {template!r}, not a path template")
    try:
        relative = template.format(**fields)
    except (KeyError, IndexError, ValueError) as e:
        raise DatasetError(f"{where}: {key} {template!r} cannot be filled for episode {episode} "
                           f"({type(e).__name__}: {e}); fields: {', '.join(fields)}") from None
    base = Path(os.path.normpath(root.absolute()))
    path = Path(os.path.normpath(base / relative))
    if not path.is_relative_to(base) or path == base:
        raise DatasetError(f"{where}: {key} {template!r} puts episode {episode}'s file at {path}, outside the "
                           f"dataset root {base}")
    return path
