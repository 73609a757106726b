"""The local executor: everything in this process, in order (what graftcache did before executors existed)."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any

from graftcache.executors import Log
from graftcache.extract import ExtractResult, extract
from graftcache.requests import ExecutorSettings, ExtractRequest, FitRequest

if TYPE_CHECKING:
    from graftcache.rollout.episodes import Simulator
    from graftcache.rollout.request import RolloutRequest
    from graftcache.rollout.teams import Team


class LocalExecutor:
    def __init__(self, settings: ExecutorSettings) -> None:
        self.settings = settings  # nothing to configure: the Ray-only fields do not apply here

    def extract(self, req: ExtractRequest, log: Log) -> ExtractResult:
        return extract(req, log=log)

    def fit(self, requests: Sequence[tuple[str, FitRequest]], log: Log, bar: Any) -> None:
        """One Plan per request, their cells run together by one LocalRunner (each backbone loaded and each cache's
        numerics probe recomputed once per command), so that cells of different requests (encoders of one token grid and
        width, suites) can share backbone passes (graftcache/fit/passes.py); with one cell per pass, request after
        request as listed."""
        from graftcache.fit.local import fit_all

        fit_all([req for _, req in requests], log, bar.update)

    def rollout_team(self, req: RolloutRequest, spawn: Callable[[], Simulator], workers: int | None,
                     log: Log) -> Team | None:
        """`workers` spawned processes on this machine (graftcache/rollout/workers.py), at most one per CPU
        (graftcache.rollout.workers.team_size); 1 (the default): none, the episodes run in the rollout's own
        process."""
        if (workers or 1) == 1:
            return None
        from graftcache.rollout.workers import Workers, team_size

        return Workers(spawn, team_size(workers, log), req)
