"""The test process's CPU scheduling, kept as it started.

SVT-AV1 (libsvtav1: lerobot's default video encoder, which tests/helpers/datasets.py writes datasets with) checks
whether it runs as root and, if so, leaves the thread that opened an encoder at SCHED_FIFO priority 99 after the
encoder is gone (measured with PyAV 16 / SVT-AV1 3.0 here). A pytest worker running as root (CI's containers, this
machine) then runs every later test, and every process it starts (Ray workers, rollout workers, forkservers), as a
real-time task: on 2 cores two such workers starve everything else, Ray's own daemons and the kernel's threads
included, and the suite slows past its budget or times out. graftcache writes H.264 only (rollout videos), so the
library is not affected; the test writers restore the policy (`scheduling_kept`) and conftest.py fails a test that
leaves its process changed (`check_scheduling`), so a new writer cannot bring it back silently.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager

#: the calling thread's (policy, priority) when this module was imported, i.e. when the pytest process started
STARTED = (os.sched_getscheduler(0), os.sched_getparam(0).sched_priority)

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


def check_scheduling(test: str) -> None:
    """Fail (after restoring it) when `test` left this process scheduled otherwise than it started."""
    now = current()
    if now != STARTED:
        restore(STARTED)
        raise AssertionError(f"{test} left this test process at {describe(now)} (it started at {describe(STARTED)}): "
                             "an encoder run as root? wrap it in helpers.scheduling.scheduling_kept()")
