"""The ray executor: extractions as shard tasks (graftcache/executors/ray_extract.py), a sweep's cells as cell
tasks (graftcache/executors/ray_fit.py), a rollout's episodes on simulator actors (graftcache/executors/ray_rollout.py),
on the cluster `settings` name (graftcache/executors/ray_cluster.py)."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any

from graftcache.executors import Log
from graftcache.extract import ExtractResult
from graftcache.requests import ExecutorSettings, ExtractRequest, FitRequest

if TYPE_CHECKING:
    from graftcache.rollout.episodes import Simulator
    from graftcache.rollout.request import RolloutRequest
    from graftcache.rollout.teams import Team


class RayExecutor:
    def __init__(self, settings: ExecutorSettings) -> None:
        self.settings = settings

    def extract(self, req: ExtractRequest, log: Log) -> ExtractResult:
        from graftcache.executors.ray_extract import extract_cache

        return extract_cache(req, self.settings, log)

    def fit(self, requests: Sequence[tuple[str, FitRequest]], log: Log, bar: Any) -> None:
        from graftcache.executors.ray_fit import fit

        fit(requests, self.settings, log, bar)

    def rollout_team(self, req: RolloutRequest, spawn: Callable[[], Simulator], workers: int | None,
                     log: Log) -> Team | None:
        from graftcache.executors.ray_rollout import Actors

        return Actors(req, spawn, workers, self.settings, log)
