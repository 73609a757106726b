"""The local executor: everything in this process, in order (what graftcache did before executors existed)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from graftcache.executors import Log
from graftcache.extract import ExtractResult, extract
from graftcache.requests import ExecutorSettings, ExtractRequest, FitRequest


class LocalExecutor:
    def __init__(self, settings: ExecutorSettings) -> None:
        self.settings = settings  # nothing to configure: the Ray-only fields do not apply here

    def extract(self, req: ExtractRequest, log: Log) -> ExtractResult:
        return extract(req, log=log)

    def fit(self, requests: Sequence[tuple[str, FitRequest]], log: Log, bar: Any) -> None:
        """One Fitter per request, all sharing one BackbonePool and one set of numerics verdicts (each backbone
        loaded and each cache's numerics probe recomputed once per run)."""
        from graftcache.backbones.pool import BackbonePool
        from graftcache.fit.run import Fitter

        backbones, numerics = BackbonePool(log), {}
        for label, req in requests:
            bar.set_postfix_str(label)
            Fitter(req, log=log, backbones=backbones, numerics=numerics).run()
            bar.update(len(req.seeds) * (1 + len(req.controls)))
