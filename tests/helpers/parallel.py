"""How `make test` runs the suite: pytest-xdist workers (`-n auto --dist loadgroup`), one more than the cores.

Why one more: on CI's 2 cores, 2 workers kept the cores 83% busy (30:27 of pytest for ~2,990 core-seconds, AMD EPYC
without avx512_bf16): a worker waiting on a subprocess's start, a lease, a server or the disk leaves its core idle,
and a third worker takes it (`workers`). The one test that needs ~10 GB at once waits for the memory first
(`wait_for_memory`), so three workers fit CI's 24 GiB.

Each worker is its own pytest session: session fixtures, temp dirs and isolated homes (helpers/env.py) are per
worker, so workers never share a cache root, a moto server (each picks a free port) or a Ray instance. What must be
arranged:

- threads: the library gives a model process every core it was granted (graftcache.runtime.granted_cpus reads
  OMP_NUM_THREADS); workers each taking every core spin against each other, so each worker (and every process
  it starts, which inherits the variable) is granted its share of the cores, at least one;
- grouping: a module runs on one worker, so its module-scoped fixtures (a trained tiny policy, an extracted cache,
  a Ray instance) are built once; modules that share session fixtures form one group;
- order: the longest groups start first, so the run does not end on one worker still busy with a long module.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import pytest

TESTS = Path(__file__).resolve().parents[1]

#: modules (paths under tests/) whose session fixtures are shared: they run on one worker, which builds them once
GROUPS = {"export/test_export": "tiny_policies", "backbones/test_zoo_backbones_cli": "tiny_policies"}

#: the longest modules (CI's --durations on 2 cores, seconds: demo ~460, tiny policies ~500, fit ~210, concurrent
#: writers ~150, released geometry ~140, gpu check ~125, remote store ~100, ray ~75), started first in this order;
#: then the other modules holding a test marked slow, then the rest, each in collection order
LONGEST = ("test_demo", "export/test_export", "backbones/test_zoo_backbones_cli", "fit/test_fit",
           "test_results_concurrent_writers", "backbones/test_released_geometry_checkpoints", "test_gpu_check",
           "store/test_store_remote", "executors/test_ray", "extract/test_extract", "encoders/test_encoders_registry",
           "cli/test_bad_input_errors", "fit/test_stream_memory", "extract/test_extract_shards")


def workers(cores: int) -> int:
    """`-n auto`'s worker count on `cores` cores: one more than the cores (see above), at most 3, the most the suite
    has been run under (each worker holds torch and its own Ray instance)."""
    return max(1, min(3, cores + 1))


def wait_for_memory(gib: float, timeout_s: float = 900.0) -> float:
    """Block until the machine has `gib` GiB available (MemAvailable), at most `timeout_s`; the seconds waited. For
    a test that needs far more memory than any other (real-size pi0.5: ~10 GB), so that it does not start while
    another worker's peak is passing. After the timeout it goes on: the test then fails or passes on its own."""
    start = time.monotonic()
    while time.monotonic() - start < timeout_s and _available_gib() < gib:
        time.sleep(2.0)
    return time.monotonic() - start


def _available_gib() -> float:
    for line in Path("/proc/meminfo").read_text().splitlines():
        if line.startswith("MemAvailable:"):
            return int(line.split()[1]) / 2**20
    return float("inf")  # not Linux: nothing to wait for


def limit_worker_threads() -> None:
    """Under xdist, grant each worker its share of the cores (OMP_NUM_THREADS) unless the caller set it."""
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
    if workers > 1:
        os.environ.setdefault("OMP_NUM_THREADS", str(max(1, len(os.sched_getaffinity(0)) // workers)))


def _module(item: pytest.Item) -> str:
    """A test module's path under tests/, without ".py" (e.g. "fit/test_fit"), as GROUPS and LONGEST name it."""
    return item.path.resolve().relative_to(TESTS).with_suffix("").as_posix()


def schedule(items: list[pytest.Item]) -> None:
    """Mark each item with its module's xdist group and move the longest modules to the front (stable, so each
    module's items keep pytest's order, which groups their fixtures)."""
    slow = {_module(item) for item in items if item.get_closest_marker("slow")}
    for item in items:
        item.add_marker(pytest.mark.xdist_group(GROUPS.get(_module(item), _module(item))))
    rank = {name: i for i, name in enumerate(LONGEST)}
    items.sort(key=lambda item: rank.get(_module(item), len(LONGEST) + (_module(item) not in slow)))
