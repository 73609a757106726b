"""Test-wide settings: fully offline, caches in temporary folders, no GPU assumptions.

Every fixture is available to every test module by argument: the ones shared across modules live in the
plugins below (tests/fixtures/), plain helpers in tests/helpers/ (imported normally).
"""

from __future__ import annotations

import os
from collections.abc import Iterator

from helpers.env import OFFLINE, isolated_homes
from helpers.parallel import check_groups, keep_order, limit_worker_threads, schedule
from helpers.scheduling import check_scheduling

os.environ.update(OFFLINE)  # before anything imports huggingface_hub
os.environ.setdefault("TOKENIZERS_PARALLELISM", "false")
limit_worker_threads()  # under pytest-xdist (`make test`), before anything imports torch

import pytest  # noqa: E402

pytest_plugins = ("fixtures.datasets", "fixtures.torch_threads", "fixtures.ray_cluster", "fixtures.s3",
                  "fixtures.resolutions", "fixtures.tiny_zoo",  # resolutions first: tiny_zoo imports it
                  "fixtures.simulator_cells")


@pytest.hookimpl(optionalhook=True)  # the suite also runs without pytest-xdist (`-p no:xdist`, a bare venv)
def pytest_xdist_auto_num_workers(config: pytest.Config) -> int:
    """`-n auto`: one worker per core this process may run on (xdist's own guess counts physical cores, which can
    be 1 on two hyperthreads), at most 2: CI's cores, and the only count the suite has been run under (each worker
    holds torch and its own Ray instance; pi0.5 at real size takes ~10 GB in one of them)."""
    return max(1, min(2, len(os.sched_getaffinity(0))))


def pytest_configure(config: pytest.Config) -> None:
    keep_order(config)


@pytest.hookimpl(tryfirst=True)  # before xdist's own hook, which reads the groups into the nodeids it schedules by
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Under xdist: each module (the tiny zoo's tests: each backbone) runs on one worker, its module- and
    session-scoped fixtures built once, the longest first (tests/helpers/parallel.py)."""
    if os.environ.get("PYTEST_XDIST_WORKER"):
        schedule(items)


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_node_collection_finished(node: object, ids: list[str]) -> None:
    check_groups(node.config, ids)


@pytest.fixture(autouse=True)
def _isolated_homes(tmp_path_factory: pytest.TempPathFactory, monkeypatch: pytest.MonkeyPatch) -> None:
    """Point every cache a test could touch (graftcache, HF hub, lerobot) at a per-session temp dir."""
    for name, value in isolated_homes(tmp_path_factory.getbasetemp()).items():
        monkeypatch.setenv(name, value)


@pytest.fixture(autouse=True)
def _scheduling_kept(request: pytest.FixtureRequest) -> Iterator[None]:
    """A test that leaves this process real-time fails, and the process is put back (tests/helpers/scheduling.py)."""
    yield
    check_scheduling(request.node.nodeid)
