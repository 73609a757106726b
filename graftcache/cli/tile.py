"""`graftcache tile`: a bigger LeRobot v3.0 dataset made of windows of a small one's frames (no encoding).

A command rather than a benchmark script because anyone testing graftcache at scale without the real
data needs it (sharded extraction, memory, LIBERO-sized runs), and benchmarks call the same function
(graftcache.datasets.tile.tile) with the same request.
"""

from __future__ import annotations

import argparse

from graftcache.cli.common import add_flag, request_from
from graftcache.requests import TileRequest


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "tile", help="build a bigger v3.0 dataset (e.g. LIBERO-sized) from windows of a small one's videos",
        description="Write a LeRobot v3.0 dataset whose episodes are windows of SOURCE's frames: its mp4s are "
        "linked, not copied or re-encoded; each episode's state and action are the source rows of the same "
        "frames. Tasks are the four LIBERO suites' real instructions (--preset libero: lerobot/libero's episode "
        "and frame counts per suite) or SOURCE's own tasks (--episodes). For measuring, not for fitting: the "
        "frames are SOURCE's scenes whatever the instruction says.")
    for name in ("source", "dest"):
        add_flag(p, TileRequest, name)
    what = p.add_mutually_exclusive_group(required=True)
    add_flag(what, TileRequest, "preset")
    add_flag(what, TileRequest, "episodes")
    add_flag(p, TileRequest, "frames")
    add_flag(p, TileRequest, "seed")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from graftcache.datasets import open_dataset, suite_of
    from graftcache.datasets.tile import tile

    dest = tile(request_from(TileRequest, args))
    meta = open_dataset(dest).meta
    per_suite: dict[str, list[int]] = {}
    for ep in meta.episodes:
        counts = per_suite.setdefault(suite_of(meta.tasks[ep.task_index]), [0, 0])
        counts[0] += 1
        counts[1] += ep.length
    print(f"{dest}: {len(meta.episodes)} episodes, {meta.n_frames} frames, {len(meta.tasks)} tasks")
    for suite, (episodes, frames) in per_suite.items():
        print(f"  {suite}: {episodes} episodes, {frames} frames")
    return 0
