"""How `make test` runs the suite on two workers (pytest-xdist, `-n auto --dist loadgroup`).

Each worker is its own pytest session: session fixtures, temp dirs and isolated homes (helpers/env.py) are per
worker, so workers never share a cache root, a moto server (each picks a free port) or a Ray instance. What must be
arranged:

- threads: the library gives a model process every core it was granted (graftcache.runtime.granted_cpus reads
  OMP_NUM_THREADS); two workers each taking both cores spin against each other, so each worker (and every process
  it starts, which inherits the variable) is granted its share of the cores;
- grouping: a module runs on one worker, so its module-scoped fixtures (an extracted cache, a Ray instance) are
  built once; modules that share session fixtures form one group (GROUPS). The tiny zoo (tests/fixtures/tiny_zoo.py)
  is the exception: its builds are shared by the workers on disk, so a test taking it runs in its backbone's group
  (`tiny_zoo-<name>`, its `name` parameter), across modules. The backbones spread over both workers, each one's
  tests find its builds made by the first of them, and a new backbone adds its cost to the run's work, not all of
  it to one worker's;
- order: the longest groups start first, so the run does not end on one worker still busy with a long group. A
  group's length is estimated from tests/durations.json (seconds per module of a clean-clone run's junit XML, written
  by `python -m devtools.suite_durations`): each of its tests counts its module's seconds over the module's tests.
  A module the file does not name counts as the longest when it holds a test marked slow (started early, a long
  one cannot end the run alone), else as the shortest.

xdist carries a test's group to its scheduler as a suffix of the test's id ("...::test_x@group"), which pytest 9.2
no longer lets it write (pytest-xdist#1386): the groups were then silently ignored, every module was split across
the workers and its module fixtures built on each (a fit of every tiny backbone twice). pyproject.toml keeps pytest
below 9.2, and `check_groups` stops a run whose ids lost their groups. With the groups in effect, xdist hands them out
largest (most tests) first unless told otherwise, which started the demo's single 330-s test last and left one worker
idle for minutes at the end: `keep_order` keeps the order `schedule` gives.
"""

from __future__ import annotations

import math
import os
from collections import Counter, defaultdict
from pathlib import Path

import pytest

from devtools.suite_durations import read

TESTS = Path(__file__).resolve().parents[1]

#: modules (paths under tests/) whose session fixtures are shared: they run on one worker, which builds them once
GROUPS = {"rollout/test_rollout": "simulator_cells", "rollout/test_rollout_workers": "simulator_cells",
          "rollout/test_rollout_ray": "simulator_cells", "rollout/test_soft_reset": "simulator_cells",
          "test_gpu_check_closed_loop": "simulator_cells"}

#: the backbone whose tiny-zoo builds the tests taking `tiny_zoo` without a `name` parameter use
#: (tests/export/test_export.py exports smolvla's cells): they run in its group
UNNAMED_BACKBONE = "smolvla"


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
    """A test module's path under tests/, without ".py" (e.g. "fit/test_fit"), as GROUPS and tests/durations.json name
    it."""
    return item.path.resolve().relative_to(TESTS).with_suffix("").as_posix()


def _group(item: pytest.Item) -> str:
    """The xdist group `item` runs in: its backbone's for a test of the tiny zoo, else its module's GROUPS group, else
    its module."""
    if "tiny_zoo" in getattr(item, "fixturenames", ()):
        callspec = getattr(item, "callspec", None)
        return f"tiny_zoo-{callspec.params.get('name', UNNAMED_BACKBONE) if callspec else UNNAMED_BACKBONE}"
    return GROUPS.get(_module(item), _module(item))


def schedule(items: list[pytest.Item], seconds: dict[str, float] | None = None) -> None:
    """Mark each item with its xdist group and order the groups longest first by `seconds` per module (default:
    tests/durations.json); the items of a group keep pytest's order, which groups their fixtures."""
    seconds = read() if seconds is None else seconds
    modules, groups = [_module(item) for item in items], [_group(item) for item in items]
    tests = Counter(modules)
    slow = {module for module, item in zip(modules, items, strict=True) if item.get_closest_marker("slow")}
    length: dict[str, float] = defaultdict(float)
    first: dict[str, int] = {}
    for i, (module, group) in enumerate(zip(modules, groups, strict=True)):
        length[group] += seconds[module] / tests[module] if module in seconds else math.inf if module in slow else 0
        first.setdefault(group, i)
    for item, group in zip(items, groups, strict=True):
        item.add_marker(pytest.mark.xdist_group(group))
    order = sorted(range(len(items)), key=lambda i: (-length[groups[i]], first[groups[i]], i))
    items[:] = [items[i] for i in order]
