"""The ray executor's fitting: one Ray task per missing cell, the driver the results file's only writer.

The driver lists each request's cells (graftcache.fit.run.Fitter.cells: identities, nothing loaded), drops
those whose run_id the results file has (and repeats: the native controls' cells are the same for every
encoder), and submits one task per cell left. A task rebuilds the Fitter from its frozen, picklable
FitRequest, fits exactly that cell, saves its projector in the shared run folder and returns its row; the
driver appends each row as its task finishes. So a driver killed mid-sweep resumes from the rows it wrote,
the results file never has two writers, and a task whose worker died is rerun by Ray (max_retries) while
finished cells, whose rows the driver already holds, are never redone.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import ray

from graftcache import results
from graftcache.backbones.pool import BackbonePool
from graftcache.encoders.fingerprint import NumericsCheck
from graftcache.errors import ExecutorError, ResultsError
from graftcache.executors import Log
from graftcache.executors.ray_cluster import (
    connect,
    finished,
    local_path,
    shared_root,
    slots,
    task_options,
    worker_compute_dtype,
)
from graftcache.fit.controls import get_control
from graftcache.fit.run import Fitter
from graftcache.requests import ExecutorSettings, FitRequest
from graftcache.runtime import set_main_threads

#: A worker process's backbones (loaded on first use), numerics verdicts (cache key -> NumericsCheck) and its last
#: request's Fitter: the worker's next cell reuses the loaded backbone, the checked caches and, of the same request,
#: the feature tables, as the local executor's next cell does.
_POOL = BackbonePool()
_NUMERICS: dict[str, NumericsCheck] = {}
_FITTER: dict[FitRequest, Fitter] = {}


def fit_cell(req: FitRequest, control: str, seed: int) -> dict[str, Any]:
    """The row of one cell, its projector saved under the request's run folder (run as `fit_cell_task`)."""
    set_main_threads()  # the CPUs Ray granted this task (it sets OMP_NUM_THREADS from num_cpus)
    if req not in _FITTER:
        _FITTER.clear()
        _FITTER[req] = Fitter(req, backbones=_POOL, numerics=_NUMERICS)
    return _FITTER[req].run_cell(get_control(control), seed)


#: The Ray task of `fit_cell`. The plain function stays the module's attribute so that cloudpickle ships it by
#: reference: the worker imports this module and keeps its own `_POOL`, `_NUMERICS` and `_FITTER`. Decorating
#: `fit_cell` itself would ship it by value, with copies of those globals (the driver's, holding its `print`).
fit_cell_task = ray.remote(fit_cell)


def shared_request(req: FitRequest, compute_dtype: str) -> FitRequest:
    """`req` as every task must read it: paths absolute, the cache root fixed, the compute dtype resolved."""
    return dataclasses.replace(req, dataset=local_path(req.dataset), policy=local_path(req.policy),
                               results=str(Path(req.results).resolve()),
                               out=req.out and str(Path(req.out).resolve()),
                               cache=shared_root(req.cache), compute_dtype=compute_dtype)


def fit(requests: Sequence[tuple[str, FitRequest]], settings: ExecutorSettings, log: Log, bar: Any) -> None:
    """Submit every missing cell of `requests`, append each row as its task finishes."""
    connect(settings, log)
    cells: dict[str, tuple[str, FitRequest, str, int]] = {}  # run_id -> (label, request, control, seed)
    folders: dict[str, Path] = {}  # run_id -> its run folder (where a row the results file cannot take is kept)
    done: dict[str, set[str]] = {}  # results file -> its run_ids
    options: dict[str, dict[str, Any]] = {}  # device -> task options
    dtypes: dict[tuple[str, str], str] = {}  # (compute dtype, device) -> as the workers resolve it
    for label, req in requests:
        if req.device not in options:
            options[req.device] = task_options(settings, req.device)
            slots(options[req.device])  # a task the cluster cannot place fails now, not after pending forever
        if (req.compute_dtype, req.device) not in dtypes:
            dtypes[req.compute_dtype, req.device] = worker_compute_dtype(req.compute_dtype, req.device,
                                                                         options[req.device])
        req = shared_request(req, dtypes[req.compute_dtype, req.device])
        seen = done.setdefault(req.results, results.done_run_ids(req.results))
        # listing cells reads the caches' index only; a Cell holds no device (the dtype is resolved)
        lister = Fitter(dataclasses.replace(req, device="cpu"), log=log)
        for control, seed, cell in lister.cells():
            if cell.run_id not in seen and cell.run_id not in cells:
                cells[cell.run_id] = (label, req, control.name, seed)
                folders[cell.run_id] = lister.run_folder(cell)
    bar.update(sum(len(r.seeds) * (1 + len(r.controls)) for _, r in requests) - len(cells))
    log(f"ray: {len(cells)} cell task(s) to run; the other cells are in the results file already")
    if any(r.cells_per_pass not in (None, 1) for _, r in requests):
        log("ray: one cell per task, so --cells-per-pass applies to the local executor only (rows record "
            "cells_per_pass 1)")
    tasks = {fit_cell_task.options(**options[req.device]).remote(req, control, seed): run_id
             for run_id, (_, req, control, seed) in cells.items()}
    refused: list[str] = []  # rows their results file could not take, each kept in its run folder
    for run_id, row in finished(tasks):
        label, req, control, seed = cells[run_id]
        if row["run_id"] != run_id:
            raise ExecutorError(f"{label} seed {seed} control {control}: the worker's cell is {row['run_id']}, "
                                f"the driver's {run_id}: do the nodes see the same policy and caches?")
        try:
            results.append_or_keep(req.results, [(row, folders[run_id])])
        except ResultsError as e:  # the row is kept in its run folder: the rows of the tasks still running too
            refused.append(str(e))
        bar.set_postfix_str(label)
        bar.update(1)
        log(f"{label} seed {seed} control {control}: eval_mse {row['eval_mse']:.4f} ({row['wall_s']:.1f}s on Ray)")
    if refused:
        raise ResultsError("; ".join(refused))
