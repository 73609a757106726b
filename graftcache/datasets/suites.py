"""LIBERO suite of a task instruction.

LeRobot LIBERO datasets carry no suite column, only task strings, so the suite is recovered from the
instruction text using resources/libero_suite_tasks.json (suite -> its instructions, from the LIBERO
benchmark's own task lists). The four evaluation suites are consulted before libero_90, because two
libero_goal / libero_10 instructions also occur in libero_90 and datasets of those suites mean the former.
"""

from __future__ import annotations

import functools
import json
from importlib import resources

UNKNOWN = "unknown"
#: Lookup priority when an instruction belongs to several suites.
SUITE_ORDER = ("libero_spatial", "libero_object", "libero_goal", "libero_10", "libero_90")
#: Every suite a cache can record (its manifest lists them in this order; `suite_index` counts in it).
SUITES = (*SUITE_ORDER, UNKNOWN)


def normalize(task: str) -> str:
    """Case, surrounding whitespace, repeated spaces and a trailing period do not change the task."""
    return " ".join(task.lower().split()).rstrip(".")


@functools.cache
def suite_tasks() -> dict[str, tuple[str, ...]]:
    """Suite name -> its instructions, as shipped in graftcache/resources/libero_suite_tasks.json."""
    text = resources.files("graftcache").joinpath("resources/libero_suite_tasks.json").read_text()
    return {suite: tuple(tasks) for suite, tasks in json.loads(text).items()}


@functools.cache
def _suite_by_task() -> dict[str, str]:
    table = suite_tasks()
    order = [s for s in SUITE_ORDER if s in table] + [s for s in table if s not in SUITE_ORDER]
    by_task: dict[str, str] = {}
    for suite in order:
        for task in table[suite]:
            by_task.setdefault(normalize(task), suite)
    return by_task


def suite_of(task: str) -> str:
    """The LIBERO suite an instruction belongs to, or "unknown" for anything else."""
    return _suite_by_task().get(normalize(task), UNKNOWN)
