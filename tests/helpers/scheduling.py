"""The test process's CPU scheduling, kept as it started.

A pytest worker running as root (CI's containers, these machines) that writes an AV1 dataset is left real-time by
SVT-AV1 (devtools/scheduling.py), and so is every later test and every process it starts (Ray workers, rollout
workers, forkservers): on 2 cores two such workers starve Ray's daemons and the kernel's threads, and the suite
slows past its budget. The writers restore the policy (devtools.scheduling.scheduling_kept); conftest.py fails a
test that leaves its process changed (`check_scheduling`), so a new writer cannot bring it back silently.
"""

from __future__ import annotations

from devtools.scheduling import current, describe, restore

#: the calling thread's (policy, priority) when this module was imported, i.e. when the pytest process started
STARTED = current()


def check_scheduling(test: str) -> None:
    """Fail (after restoring it) when `test` left this process scheduled otherwise than it started."""
    now = current()
    if now != STARTED:
        restore(STARTED)
        raise AssertionError(f"{test} left this test process at {describe(now)} (it started at {describe(STARTED)}): "
                             "an encoder run as root? wrap it in devtools.scheduling.scheduling_kept()")
