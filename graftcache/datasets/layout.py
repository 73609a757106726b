"""Where each episode's bytes live on disk: the output of a version reader (v2.py, v3.py).

Plain frozen dataclasses of paths and numbers, so a `LeRobotSource` pickles cheaply into data-loader
workers and no file handle crosses a process boundary.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from graftcache.datasets.meta import EpisodeMeta


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
    """A version reader's answer: tasks, episodes (ascending), their files, and the files to fingerprint."""

    tasks: tuple[str, ...]
    episodes: tuple[EpisodeMeta, ...]
    files: tuple[EpisodeFiles, ...]  # aligned with `episodes`
    meta_files: tuple[Path, ...]
