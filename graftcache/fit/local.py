"""A fit in this process: `LocalRunner` runs the passes graftcache.fit.passes.run_passes hands it, one at a time,
through graftcache.fit.run.run_pass; `fit_all` (the local executor's sweep) and `Fitter` (`graftcache fit`) run the
missing cells of their requests with one. Imports go one way: this module -> passes (which cells, claims, rows
written) and -> run (one pass); neither of those imports the other.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

from graftcache.backbones.loaded import LoadedBackbones
from graftcache.encoders.fingerprint import NumericsCheck
from graftcache.fit.materials import Materials
from graftcache.fit.passes import run_passes
from graftcache.fit.plan import Plan, Planned
from graftcache.fit.run import run_pass
from graftcache.requests import FitRequest

__all__ = ["Fitter", "LocalRunner", "fit_all"]


class LocalRunner:
    """Passes in this process, one at a time (graftcache.fit.passes.Runner), each request's Materials made on its
    first pass and dropped once it has no cell left; the backbones and numerics verdicts are shared by all."""

    slots = 1

    def __init__(self, backbones: LoadedBackbones, numerics: dict[str, NumericsCheck] | None = None) -> None:
        self.backbones = backbones
        self.numerics = {} if numerics is None else numerics
        self._materials: dict[int, Materials] = {}  # id(plan) -> its materials
        self._queue: list[tuple[int, Sequence[Planned]]] = []
        self._tickets = 0

    def materials(self, plan: Plan) -> Materials:
        if id(plan) not in self._materials:
            self._materials[id(plan)] = Materials(plan, self.backbones, self.numerics)
        return self._materials[id(plan)]

    def to_run(self, cells: Sequence[Planned]) -> None:
        """Nothing to say: each pass's rows are told as they come."""

    def submit(self, cells: Sequence[Planned]) -> int:
        self._tickets += 1
        self._queue.append((self._tickets, cells))
        return self._tickets

    def next_done(self) -> tuple[int, list[dict[str, Any]]]:
        ticket, cells = self._queue.pop(0)
        return ticket, run_pass(cells, self.materials)

    def finished(self, plan: Plan) -> None:
        mat = self._materials.pop(id(plan), None)
        if mat is not None:
            mat.close()

    def cancel(self) -> None:
        self._queue.clear()


def fit_all(requests: Sequence[FitRequest], log: Callable[[str], None] = print,
            visited: Callable[[int], None] = lambda n: None) -> list[dict[str, Any]]:
    """Every missing cell of `requests` in this process, cells of different requests (encoders of one grid and
    width, suites) sharing backbone passes, each policy loaded and each cache's numerics checked once."""
    plans = [Plan(req, log) for req in requests]
    return run_passes(plans, LocalRunner(LoadedBackbones(log)), visited)


class Fitter:
    """The cells of one FitRequest in this process: its Plan, Materials and a LocalRunner; `run()` returns the
    rows it wrote."""

    def __init__(self, req: FitRequest, log: Callable[[str], None] = print,
                 backbones: LoadedBackbones | None = None, numerics: dict[str, NumericsCheck] | None = None) -> None:
        """`backbones` and `numerics` (cache key -> verdict) may be shared by the Fitters of one process, so each
        policy is loaded and each cache's numerics probe recomputed once per process."""
        self.plan = Plan(req, log)
        self.runner = LocalRunner(backbones or LoadedBackbones(log), numerics)

    def run(self) -> list[dict[str, Any]]:
        """Every missing cell, `cells_per_pass` cells to a pass of the backbone where they can share one
        (graftcache/fit/passes.py), each row appended to the results file as its pass finishes."""
        return run_passes([self.plan], self.runner)
