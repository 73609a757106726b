"""Recording a finished episode: its video (a simulator built to record frames) and its row in the rollouts file.

Each episode's video is written whole (a temporary name, synced, then renamed) under videos/ beside the rollouts file
before its row is appended, and the row names it relative to the file; so a row never names a partial video, and an
episode rerun because its row is missing overwrites its video. Rows are appended under the file's lease
(graftcache.results.writing.append_table), safe across processes.
"""

from __future__ import annotations

import os
import socket
import uuid
from collections.abc import Iterable, Mapping
from dataclasses import asdict, fields
from pathlib import Path
from typing import Any

import polars as pl

import graftcache
from graftcache.errors import RolloutError
from graftcache.results.writing import append_table, fsync
from graftcache.rollout import rollouts_file
from graftcache.rollout.episodes import Episode, EpisodeReport, Outcome, Simulator, where
from graftcache.rollout.graded import Graded
from graftcache.rollout.schedule import VIDEOS_FOLDER
from graftcache.upstream import installed

GRADED_FIELDS = tuple(f.name for f in fields(Graded))  # the row's columns of an Outcome's `graded`


def video_of(episode: Episode) -> str:
    """The episode's video, relative to the rollouts file: named by every field of its episode_id, so episodes of
    other seeds, step limits or perturbations never share one."""
    perturbed = f"_perturb{episode.perturbation_m:g}m" if episode.perturbation_m else ""
    return (f"{VIDEOS_FOLDER}/{episode.run_id}/{episode.suite}_task{episode.task_index}_ep{episode.episode}"
            f"_seed{episode.seed}_max{episode.max_steps}{perturbed}.mp4")


def write_video(path: Path, outcome: Outcome) -> None:
    """The outcome's frames as lerobot-eval writes its videos (lerobot.utils.io_utils.write_video: H.264, yuv420p,
    at the env's render fps), to a temporary name beside `path`, synced and renamed over it: `path` is whole or
    absent (an older one is replaced). The temporary file never outlives the call (kill -9 aside)."""
    from lerobot.utils.io_utils import write_video as lerobot_write_video

    path.parent.mkdir(parents=True, exist_ok=True)
    # ends in .mp4: the container is chosen by the name
    tmp = path.with_name(f".{path.stem}.{socket.gethostname()}.{os.getpid()}.{uuid.uuid4().hex[:8]}.tmp.mp4")
    try:
        lerobot_write_video(tmp, list(outcome.frames), outcome.fps)
        fsync(tmp)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    try:  # the rename survives a crash once its folder is synced, as the row's append does for the rollouts file
        fsync(path.parent)
    except OSError:
        pass


def row_of(episode: Episode, outcome: Outcome, command: str, video: str | None = None) -> dict[str, Any]:
    """The rollouts row of a finished episode (graftcache.rollout.rollouts_file.SCHEMA); `video`: its path, relative
    to the rollouts file. What the simulator did not measure (an Outcome without `graded` or `target_offset_m`) is
    null."""
    graded = asdict(outcome.graded) if outcome.graded is not None else dict.fromkeys(GRADED_FIELDS)
    offset_x, offset_y = outcome.target_offset_m if outcome.target_offset_m is not None else (None, None)
    return {"episode_id": episode.id, "format_version": rollouts_file.FORMAT_VERSION, "run_id": episode.run_id,
            "suite": episode.suite, "task_index": episode.task_index, "episode": episode.episode,
            "seed": episode.seed, "init_state": outcome.init_state, "max_steps": episode.max_steps,
            "success": outcome.success, "steps": outcome.steps, "seconds": outcome.seconds, "video": video,
            "perturbation_m": episode.perturbation_m, "target_offset_x_m": offset_x, "target_offset_y_m": offset_y,
            **graded, "kernels": outcome.kernels, "lerobot_version": installed("lerobot"),
            "graftcache_version": graftcache.__version__, "command": command}


def append(path: str | Path, rows: Iterable[Mapping[str, Any]]) -> pl.DataFrame:
    """Append episodes' rows (dicts of graftcache.rollout.rollouts_file.SCHEMA's columns) under the file's lease;
    an episode already there is replaced, never doubled."""
    new = rollouts_file.validate(pl.DataFrame([dict(r) for r in rows], schema=rollouts_file.SCHEMA))
    return append_table(path, new, rollouts_file.read, key="episode_id", what="rollouts file")


def with_video(rollouts: Path, command: str, episode: Episode, outcome: Outcome) -> dict[str, Any]:
    """A finished episode's row, its video (when it has frames) written first: the row, which names it, is for the
    caller to append (a Ray actor's row goes back to the driver, graftcache.executors.ray_rollout)."""
    video = None
    if outcome.frames is not None:
        video = video_of(episode)
        write_video(rollouts.parent / video, outcome)
    return row_of(episode, outcome, command, video)


def record(rollouts: Path, command: str, episode: Episode, outcome: Outcome) -> EpisodeReport:
    """Write a finished episode, its video (when it has frames) before its row, which names it, and report it."""
    row = with_video(rollouts, command, episode, outcome)
    append(rollouts, [row])
    return EpisodeReport.of(row)


def run_one(sim: Simulator, row: Mapping[str, Any], episode: Episode, rollouts: Path, command: str) -> EpisodeReport:
    """Run one episode on `sim` and `record` it as the simulator yields it, before its generator is resumed to its
    end: an error the simulator raises after its episode leaves the episode written."""
    reports = [record(rollouts, command, episode, outcome) for outcome in sim.run(row, [episode])]
    if len(reports) != 1:
        raise RolloutError(f"{where(episode)}: the simulator gave {len(reports)} outcomes for one episode")
    return reports[0]
