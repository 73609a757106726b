"""`python -m devtools.tile`: a bigger LeRobot v3.0 dataset made of windows of a small one's frames (no encoding).

Its flags come from TileRequest's `setting(...)` declarations through graftcache.cli.common.add_flag, as every
graftcache command's do, so ranges and help are declared once; errors are one line and exit 2, as there.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from devtools.tile import TileRequest, tile
from graftcache.cli.common import add_flag, request_from
from graftcache.errors import GraftcacheError

PROG = "python -m devtools.tile"


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=PROG,
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
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Build the dataset and print its episodes and frames per suite; a GraftcacheError is one line, exit 2."""
    from graftcache.datasets import open_dataset, suite_of

    args = build_parser().parse_args(argv)
    try:
        dest = tile(request_from(TileRequest, args))
    except GraftcacheError as e:
        print(f"{PROG}: error: {e}", file=sys.stderr)
        return 2
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
