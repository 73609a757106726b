"""The ray executor's fitting: a Ray task per backbone pass (1..N cells), under the same claims as the local executor.

The driver makes every request's Plan (graftcache.fit.plan.Plan: identities, pass keys, nothing loaded) and runs the one
claim-and-run loop the local executor runs (graftcache.fit.passes.run_passes), with passes going to Ray tasks
(`RayRunner`) instead of this process: it claims a pass's cells (graftcache.results.claims.cell_claim), submits the pass
as one task, and appends the task's rows once it finishes, then gives the claims back. So `--cells-per-pass` reaches
the cluster (a fused pass is one task), two drivers (or a driver and a local fit) writing one results file share
its cells instead of both computing each, a driver killed mid-sweep resumes from the rows it wrote, and a task whose
worker died is rerun by Ray (max_retries) while finished cells, whose rows are written, are never redone.

A task rebuilds each request's Plan from its frozen, picklable FitRequest and runs the pass as the local executor
does (graftcache.fit.run.run_pass): projectors are saved in the shared run folders, rows returned to the driver.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import ray

from graftcache.backbones.loaded import LoadedBackbones
from graftcache.encoders.fingerprint import NumericsCheck
from graftcache.errors import ExecutorError
from graftcache.executors import Log
from graftcache.executors.ray_cluster import (
    connect,
    local_path,
    result,
    shared_root,
    slots,
    task_options,
    worker_compute_dtype,
)
from graftcache.fit.controls import get_control
from graftcache.fit.materials import Materials
from graftcache.fit.passes import run_passes
from graftcache.fit.plan import Plan, Planned
from graftcache.fit.run import run_pass
from graftcache.requests import ExecutorSettings, FitRequest
from graftcache.runtime import set_main_threads

#: A worker process's backbones (loaded on first use), numerics verdicts (cache key -> NumericsCheck), and the plans
#: and materials of its last requests: the worker's next pass reuses the loaded backbone, the checked caches and,
#: of the same requests, the feature tables, as the local executor's next pass does.
_POOL = LoadedBackbones()
_NUMERICS: dict[str, NumericsCheck] = {}
_KEPT: dict[FitRequest, Materials] = {}
#: Requests whose plans and tables a worker keeps (a pass may hold cells of several: encoders of one grid, suites).
KEEP = 8

#: One cell of a pass as a task receives it: its request, its control's name and its seed.
TaskCell = tuple[FitRequest, str, int]


def _materials(req: FitRequest) -> Materials:
    if req not in _KEPT:
        while len(_KEPT) >= KEEP:
            _KEPT.pop(next(iter(_KEPT))).close()
        _KEPT[req] = Materials(Plan(req, log=print), _POOL, _NUMERICS)
    return _KEPT[req]


def fit_cells(cells: Sequence[TaskCell]) -> list[dict[str, Any]]:
    """The rows of one pass of cells, their projectors saved in their run folders (run as `fit_cells_task`)."""
    set_main_threads()  # the CPUs Ray granted this task (it sets OMP_NUM_THREADS from num_cpus)
    of_pass = []
    for req, control, seed in cells:
        plan = _materials(req).plan
        of_pass.append((plan, plan.cell(get_control(control), seed)))
    return run_pass(of_pass, lambda plan: _materials(plan.req))


#: The Ray task of `fit_cells`. The plain function stays the module's attribute so that cloudpickle ships it by
#: reference: the worker imports this module and keeps its own `_POOL`, `_NUMERICS` and `_KEPT`. Decorating
#: `fit_cells` itself would ship it by value, with copies of those globals (the driver's, holding its `print`).
fit_cells_task = ray.remote(fit_cells)


def shared_request(req: FitRequest, compute_dtype: str) -> FitRequest:
    """`req` as every task must read it: paths absolute, the cache root fixed, the compute dtype resolved."""
    return dataclasses.replace(req, dataset=local_path(req.dataset), policy=local_path(req.policy),
                               results=str(Path(req.results).resolve()),
                               out=req.out and str(Path(req.out).resolve()),
                               cache=shared_root(req.cache), compute_dtype=compute_dtype)


class RayRunner:
    """Passes as Ray tasks (graftcache.fit.passes.Runner), as many in flight as the cluster runs at once."""

    def __init__(self, options: Mapping[str, dict[str, Any]], labels: Mapping[FitRequest, str], log: Log,
                 bar: Any) -> None:
        self.options, self.labels, self.log, self.bar = options, labels, log, bar
        self.slots = max(1, min(slots(o) for o in options.values()))
        self._running: dict[ray.ObjectRef, tuple[int, Sequence[Planned]]] = {}
        self._tickets = 0

    def to_run(self, cells: Sequence[Planned]) -> None:
        self.log(f"ray: {len(cells)} cell task(s) to run; the other cells are in the results file already, or "
                 "copied from a run of the same policy")

    def submit(self, cells: Sequence[Planned]) -> int:
        self._tickets += 1
        device = cells[0][0].req.device
        tasks = [(plan.req, cell.control, cell.seed) for plan, cell in cells]
        self._running[fit_cells_task.options(**self.options[device]).remote(tasks)] = (self._tickets, cells)
        return self._tickets

    def next_done(self) -> tuple[int, list[dict[str, Any]]]:
        (ready,), _ = ray.wait(list(self._running), num_returns=1)
        ticket, cells = self._running.pop(ready)
        plan, first = cells[0]
        rows = result(ready, f"{self.labels[plan.req]} seed {first.seed} control {first.control}")
        for (plan, cell), row in zip(cells, rows, strict=True):
            label = self.labels[plan.req]
            if row["run_id"] != cell.run_id:
                raise ExecutorError(f"{label} seed {cell.seed} control {cell.control}: the worker's cell is "
                                    f"{row['run_id']}, the driver's {cell.run_id}: do the nodes see the same "
                                    "policy and caches?")
            self.bar.set_postfix_str(label)
            shared = f", its share of a pass of {len(cells)}" if len(cells) > 1 else ""
            self.log(f"{label} seed {cell.seed} control {cell.control}: eval_mse {row['eval_mse']:.4f} "
                     f"({row['wall_s']:.1f}s on Ray{shared})")
        return ticket, rows

    def finished(self, plan: Plan) -> None:
        """Nothing is kept here: the workers keep their own tables."""

    def cancel(self) -> None:
        for ref in self._running:
            ray.cancel(ref, force=True)
        self._running.clear()


def fit(requests: Sequence[tuple[str, FitRequest]], settings: ExecutorSettings, log: Log, bar: Any) -> None:
    """Every missing cell of `requests`, a pass per task, each pass's rows appended as its task finishes."""
    connect(settings, log)
    options: dict[str, dict[str, Any]] = {}  # device -> task options
    dtypes: dict[tuple[str, str], str] = {}  # (compute dtype, device) -> as the workers resolve it
    plans, labels = [], {}
    for label, req in requests:
        if req.device not in options:
            options[req.device] = task_options(settings, req.device)
            slots(options[req.device])  # a task the cluster cannot place fails now, not after pending forever
        if (req.compute_dtype, req.device) not in dtypes:
            dtypes[req.compute_dtype, req.device] = worker_compute_dtype(req.compute_dtype, req.device,
                                                                         options[req.device])
        req = shared_request(req, dtypes[req.compute_dtype, req.device])
        # a Plan reads the caches' index and the policy's config only: the driver needs no GPU
        plan = Plan(req, log=log, check_device=False)
        plans.append(plan)
        labels[plan.req] = label
    run_passes(plans, RayRunner(options, labels, log, bar), bar.update)
