"""The calling thread's CPU scheduling, kept across a block that encodes AV1 video.

SVT-AV1 (libsvtav1: lerobot's default video encoder) checks whether it runs as root and, if so, leaves the thread
that opened an encoder at SCHED_FIFO priority 99 after the encoder is gone (measured with PyAV 16 / SVT-AV1 3.0,
tests/test_suite_scheduling.py). Whatever that thread runs next, and every process it starts, then runs as a
real-time task: on 2 cores, two such processes starve everything else, the kernel's threads included. graftcache
itself writes H.264 only (rollout videos), so the library never needs this; the writers beside it do: the tests'
dataset writers (tests/helpers/datasets.py), benchmarks/bench_reader.py's synthetic dataset, data/pack_sample.py.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager

POLICIES = {os.SCHED_OTHER: "SCHED_OTHER", os.SCHED_FIFO: "SCHED_FIFO", os.SCHED_RR: "SCHED_RR",
            os.SCHED_BATCH: "SCHED_BATCH", os.SCHED_IDLE: "SCHED_IDLE"}


def current() -> tuple[int, int]:
    """The calling thread's (policy, priority): pid 0 is the calling thread for Linux's sched_* calls."""
    return os.sched_getscheduler(0), os.sched_getparam(0).sched_priority


def restore(to: tuple[int, int]) -> None:
    os.sched_setscheduler(0, to[0], os.sched_param(to[1]))


def describe(state: tuple[int, int]) -> str:
    return f"{POLICIES.get(state[0], state[0])} priority {state[1]}"


@contextmanager
def scheduling_kept() -> Iterator[None]:
    """The calling thread's scheduling policy and priority as they were before the block, whatever ran in it."""
    before = current()
    try:
        yield
    finally:
        if current() != before:
            restore(before)
