"""Executors: where the work of `extract`, `sweep` and `rollout` runs, a registry chosen by name (`--executor`).

- local  this process, one cache or cell after the other (the default; every executor must write what it writes);
         a rollout's episodes here, or in `--workers N` spawned processes (graftcache/rollout/workers.py)
- ray    Ray tasks on a cluster, started here or joined at `--address`: an extraction becomes one task per shard
         of the cache's blocks (graftcache/executors/ray_extract.py), a sweep's fitting one task per backbone
         pass of missing cells, under the same claims as the local executor (graftcache/executors/ray_fit.py), a
         rollout's episodes calls of Ray actors that each hold a simulator (graftcache/executors/ray_rollout.py)

Entries are import strings (graftcache.lazy), so Ray is imported only when the ray executor is chosen.
Every executor does the same two jobs on the same requests; only where they run differs, so the caches,
run_ids and rows do not depend on the executor.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any, Protocol

from graftcache.errors import ExecutorError, GraftcacheError
from graftcache.lazy import import_string
from graftcache.requests import ExecutorSettings

if TYPE_CHECKING:
    from graftcache.extract import ExtractResult
    from graftcache.requests import ExtractRequest, FitRequest
    from graftcache.rollout.episodes import Simulator
    from graftcache.rollout.request import RolloutRequest
    from graftcache.rollout.teams import Team

Log = Callable[[str], None]

EXECUTORS: dict[str, str] = {
    "local": "graftcache.executors.local:LocalExecutor",
    "ray": "graftcache.executors.ray_executor:RayExecutor",
}


class Executor(Protocol):
    """What `extract`, `sweep` and `rollout` hand their work to."""

    def extract(self, req: ExtractRequest, log: Log) -> ExtractResult:
        """One complete cache for `req` (reused, resumed or written)."""

    def fit(self, requests: Sequence[tuple[str, FitRequest]], log: Log, bar: Any) -> None:
        """Every missing cell of the (label, request) pairs, each row appended to its request's results file;
        `bar` (graftcache.progress.progress) advances by one per cell visited, skipped cells included."""

    def rollout_team(self, req: RolloutRequest, spawn: Callable[[], Simulator], workers: int | None,
                     log: Log) -> Team | None:
        """The team that will run `req`'s missing episodes (graftcache.rollout.teams.Team), started now, `workers`
        simulators each built by `spawn` (None: the executor's default); None: in the rollout's own process."""


def check_executor(name: str) -> None:
    if name not in EXECUTORS:
        raise GraftcacheError(f"executor {name!r}: choose one of {', '.join(EXECUTORS)}")


def get_executor(settings: ExecutorSettings) -> Executor:
    """The executor `settings` names, built from them; a library it needs that is not installed is one line."""
    check_executor(settings.executor)
    try:
        executor = import_string(EXECUTORS[settings.executor])
    except ModuleNotFoundError as e:
        if (e.name or "graftcache").startswith("graftcache"):
            raise
        raise ExecutorError(f"--executor {settings.executor} needs {e.name}, which is not installed here: "
                            f"pip install 'graftcache[{settings.executor}]'") from None
    return executor(settings)
