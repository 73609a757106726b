"""How `make test` runs the suite on two workers (pytest-xdist, `-n auto --dist loadgroup`).

Each worker is its own pytest session: session fixtures, temp dirs and isolated homes (helpers/env.py) are per
worker, so workers never share a cache root, a moto server (each picks a free port) or a Ray instance. What must be
arranged:

- threads: the library gives a model process every core it was granted (graftcache.runtime.granted_cpus reads
  OMP_NUM_THREADS); two workers each taking both cores spin against each other, so each worker (and every process
  it starts, which inherits the variable) is granted its share of the cores;
- grouping: a module runs on one worker, so its module-scoped fixtures (a trained tiny policy, an extracted cache,
  a Ray instance) are built once; modules that share session fixtures form one group;
- order: the longest groups start first, so the run does not end on one worker still busy with a long module.

xdist carries a test's group to its scheduler as a suffix of the test's id ("...::test_x@group"), which pytest 9.2
no longer lets it write (pytest-xdist#1386): the groups were then silently ignored, every module was split across
the workers and its module fixtures built on each (a fit of every tiny backbone twice). pyproject.toml keeps pytest
below 9.2, and `check_groups` stops a run whose ids lost their groups. With the groups in effect, xdist hands them out
largest (most tests) first unless told otherwise, which started the demo's single 330-s test last and left one worker
idle for minutes at the end: `keep_order` keeps the order `schedule` gives.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

TESTS = Path(__file__).resolve().parents[1]

#: modules (paths under tests/) whose session fixtures are shared: they run on one worker, which builds them once
GROUPS = {"export/test_export": "tiny_policies", "backbones/test_zoo_backbones_cli": "tiny_policies",
          "rollout/test_rollout": "simulator_cells", "rollout/test_rollout_workers": "simulator_cells",
          "rollout/test_rollout_ray": "simulator_cells"}

#: the longest groups (a GROUPS group ranks as its module listed here), from a clean-clone run's junit times on 2 cores
#: (2026-11-28, AMD EPYC with avx512_bf16, seconds: demo 332, simulator cells 226, tiny policies 162, remote store
#: 148, fit 127, ray 125, concurrent writers 114, bad input 106, released geometry 102, encoders 74, gpu check 73),
#: started first in this order; then the other modules holding a test marked slow, then the rest, in collection order
LONGEST = ("test_demo", "rollout/test_rollout_workers", "export/test_export", "store/test_store_remote", "fit/test_fit",
           "executors/test_ray", "test_results_concurrent_writers", "cli/test_bad_input_errors",
           "backbones/test_released_geometry_checkpoints", "encoders/test_encoders_registry", "test_gpu_check",
           "fit/test_stream_memory", "extract/test_extract", "extract/test_extract_shards")


def limit_worker_threads() -> None:
    """Under xdist, grant each worker its share of the cores (OMP_NUM_THREADS) unless the caller set it."""
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
    if workers > 1:
        os.environ.setdefault("OMP_NUM_THREADS", str(max(1, len(os.sched_getaffinity(0)) // workers)))


def keep_order(config: pytest.Config) -> None:
    """On xdist's controller: hand the groups out in the order `schedule` sorted them (longest first), not by their
    number of tests (xdist's `--loadscope-reorder` default)."""
    if hasattr(config.option, "loadscopereorder"):
        config.option.loadscopereorder = False


def check_groups(config: pytest.Config, ids: list[str]) -> None:
    """On xdist's controller under `--dist loadgroup`, as a worker reports the ids it collected: stop the run when
    they lack the groups `schedule` gave them (a pytest xdist cannot write them into)."""
    lost = [nodeid for nodeid in ids if "@" not in nodeid.rpartition("]")[2]]
    if config.getvalue("dist") == "loadgroup" and lost:
        pytest.exit(f"pytest-xdist's loadgroup dropped the group of {len(lost)} test(s), e.g. {lost[0]} (pytest "
                    f"{pytest.__version__}; pytest-xdist#1386): install the pytest pyproject.toml names "
                    "(scripts/setup.sh)", returncode=pytest.ExitCode.USAGE_ERROR)


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
