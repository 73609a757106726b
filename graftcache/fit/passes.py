"""Several cells per pass of the frozen backbone: which cells share one, how many, and the loop that runs them.

The backbone is frozen and the same for every cell of a (backbone, policy) pair, and a graft cell trains only a
projector, so cells that feed the backbone token grids of one shape (seeds, the image controls, encoders of one
grid and width) can share its forward and backward: each projector projects its own cell's rows of one
concatenated batch (graftcache.graft.FusedProjector), and each cell keeps its own loss, optimiser state, gradient
clipping and random streams (graftcache.fit.loop.optimise_together), so its row equals the row it gets alone
up to float rounding of the larger batch. Held-out scoring is shared the same way.

Which cells run alone (`graftcache.fit.plan.Plan.pass_key` is None for them): the `lora` control (LoRA adapts the
backbone every row of a pass goes through), the `align` objective (a closed-form ridge: no backbone pass to share),
controls that train nothing (`native`: scored as loaded) and backbones whose loss is one mean over the batch
(pi0-FAST's cross-entropy: `graftcache.backbones.spec.BackboneSpec.loss_per_sample` False). The `cells_per_pass` a
request asks for only groups cells; it is an execution setting like the reader count, so no cell (hence no run_id)
depends on it, and a rerun whose pass is partly done runs only its missing cells. Rows record how many cells their
pass held (`cells_per_pass`) and, as `wall_s`, their share of the pass's time.

The default (the backbone's spec, `cells_per_pass` by device type) is what benchmarks/bench_fuse.py and
benchmarks/gpu_check.py measured cheapest per cell; the numbers are in the files they wrote, not here. On CPU, 1:
at tiny size no gain stood out of the noise, and at SmolVLA's released size the step is compute-bound while every
cell of a pass holds its own shuffle buffer (benchmarks/results/bench_fuse_cpu_run1.json, bench_fuse_cpu_run2.json,
bench_fuse_cpu_smolvla_released.json). On CUDA, 4 for SmolVLA, whose step is latency-bound, and 1 for pi0.5, which
is near its MFU alone and memory-bound at the paper's batch (benchmarks/results/gpu_check_*.json, one per card;
docs/scale.md's GPU table quotes them).
A pass that would not fit is refused before its first step (graftcache.fit.step_memory,
naming --cells-per-pass).
"""

from __future__ import annotations

import time
from collections import Counter
from collections.abc import Callable, Sequence
from contextlib import ExitStack
from typing import Any, Protocol

import polars as pl
import torch

from graftcache import results
from graftcache.backbones import get_backbone
from graftcache.errors import ResultsError
from graftcache.file_lease import FileLease
from graftcache.fit.plan import Plan, Planned
from graftcache.results.claims import append_or_keep, cell_claim, drop_claims_folder
from graftcache.runtime import set_main_threads


def default_cells_per_pass(backbone: str, device: torch.device) -> int:
    """Cells per backbone pass when a request does not say: the backbone's spec, by device type
    (graftcache.backbones.spec.BackboneSpec.cells_per_pass; SmolVLA's and pi0.5's measured by benchmarks/bench_fuse.py
    and benchmarks/gpu_check.py); unlisted: 1."""
    return get_backbone(backbone).spec.cells_per_pass.get(device.type, 1)


def place(c: Planned) -> tuple[str, str]:
    """(results file, run_id): a cell's row's place, the same for a cell two requests share."""
    plan, cell = c
    return plan.req.results, cell.run_id


def group_passes(cells: Sequence[Planned]) -> list[list[Planned]]:
    """`cells` cut into passes: those of one pass key in runs of their request's `cells_per_pass` (by default the
    backbone's spec on its device), each cell with no key alone; passes in the order of their first cell
    (so with 1 cell per pass, the cells' order)."""
    groups: dict[Any, list[int]] = {}
    for i, (plan, cell) in enumerate(cells):
        key = plan.pass_key(plan.control(cell))
        groups.setdefault(("alone", i) if key is None else key, []).append(i)
    passes = []
    for at in groups.values():
        plan = cells[at[0]][0]
        n = (plan.req.cells_per_pass or default_cells_per_pass(plan.req.backbone, plan.device)) if len(at) > 1 else 1
        passes += [at[i:i + n] for i in range(0, len(at), n)]
    return [[cells[i] for i in p] for p in sorted(passes)]


class Runner(Protocol):
    """Where passes run: this process (graftcache.fit.local.LocalRunner) or Ray tasks
    (graftcache.executors.ray_fit.RayRunner). `run_passes` claims a pass's cells before it submits the pass and
    writes its rows, so every runner computes a cell only under its claim."""

    slots: int  # passes in flight at once

    def to_run(self, cells: Sequence[Planned]) -> None:
        """The cells left to run once finished ones are skipped (before any is claimed)."""

    def submit(self, cells: Sequence[Planned]) -> int:
        """Start a pass; returns its ticket."""

    def next_done(self) -> tuple[int, list[dict[str, Any]]]:
        """(ticket, rows in the pass's order) of a submitted pass, as one finishes."""

    def finished(self, plan: Plan) -> None:
        """`plan` has no cell left to run here: what was kept for its cells may go."""

    def cancel(self) -> None:
        """Stop the passes still running (the loop stops early: an error, Ctrl-C)."""


def _take(claim: FileLease) -> bool:
    """Take a cell's claim; where no claim can be made (a read-only place) the cell runs unclaimed, and its row
    is then kept by graftcache.results.claims.append_or_keep."""
    try:
        return claim.try_acquire()
    except OSError:
        return True


def release_all(claims: Sequence[FileLease]) -> None:
    """Give back every claim of a pass, also when Ctrl-C or SIGTERM lands while one is given back (it is raised once
    all are): a claim left behind outlives its finished cell."""
    with ExitStack() as stack:
        for claim in claims:
            stack.callback(claim.release)


def _write(cells: Sequence[Planned], rows: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """Append the rows of a pass's cells to their results files, each file's rows at once; the rows a file cannot
    take are all kept in their cells' run folders (graftcache.results.claims.append_or_keep), then one ResultsError
    names them."""
    files: dict[str, list[tuple[dict[str, Any], Any]]] = {}
    for (plan, cell), row in zip(cells, rows, strict=True):
        files.setdefault(plan.req.results, []).append((row, plan.run_folder(cell)))
    refused = []
    for path, pairs in files.items():
        try:
            append_or_keep(path, pairs)
        except ResultsError as e:
            refused.append(str(e))
    if refused:
        raise ResultsError("; ".join(refused))
    return list(rows)


def missing_cells(plans: Sequence[Plan], visited: Callable[[int], None] = lambda n: None) -> list[Planned]:
    """The cells of `plans` whose rows their results files lack, each once (a cell two requests share, such as the
    native controls of every encoder, is the first request's); the others are said skipped and `visited`."""
    missing: list[Planned] = []
    seen: set[tuple[str, str]] = set()
    shared: Counter[str] = Counter()  # control -> cells of an earlier request too
    done = {path: results.done_run_ids(path) for path in {p.req.results for p in plans}}
    for plan in plans:
        finished = []
        for cell in plan.cells():
            at = place((plan, cell))
            if at in seen:  # a cell two requests share (the native controls of every encoder) runs once
                shared[cell.control] += 1
                visited(1)
                continue
            seen.add(at)
            if cell.run_id in done[plan.req.results]:
                finished.append(cell)
                visited(1)
            else:
                missing.append((plan, cell))
        if finished:
            plan.skipped(finished)
    if shared:
        which = ", ".join(f"{control} {n}" for control, n in shared.items())
        plans[0].log(f"{shared.total()} cells are cells of earlier requests too ({which}): each computed once")
    return missing


#: A missing cell whose policy another run already is (or will be, earlier in the same command): that run's row, as
#: its results file holds it, or that cell, whose row the copy waits for.
Copy = tuple[Planned, "dict[str, Any] | Planned"]


def separate_copies(cells: Sequence[Planned]) -> tuple[list[Planned], list[Copy]]:
    """`cells` split into those to fit and those whose policy (graftcache.fit.plan.Plan.policy_id: the function
    rolled out and the frames scored) is a run's already: a row of their results file, else the first such cell of
    `cells`. Separated before passes are formed, so that no pass (of this process or a Ray task) fits a policy twice."""
    known: dict[str, dict[str, dict[str, Any]]] = {}  # results file -> policy_id -> its first row there
    first: dict[str, Planned] = {}  # policy_id -> the cell of `cells` that fits it
    fit, copies = [], []
    for plan, cell in cells:
        path = plan.req.results
        if path not in known:
            table = results.read(path)
            known[path] = {r["policy_id"]: r for r in table.reverse().iter_rows(named=True) if r["policy_id"]}
        policy = plan.policy_id(cell)
        original = known[path].get(policy) or first.get(policy)
        if original is None:
            first[policy] = (plan, cell)
            fit.append((plan, cell))
        else:
            copies.append(((plan, cell), original))
    return fit, copies


def _original_row(original: dict[str, Any] | Planned, written: dict[tuple[str, str], dict[str, Any]]) -> dict[str, Any]:
    """The row a copy is made from: a row of its file, or its original cell's as written by this command (else as
    its results file holds it: another process computed it)."""
    if isinstance(original, dict):
        return original
    if place(original) not in written:
        table = results.read(original[0].req.results).filter(pl.col("run_id") == original[1].run_id)
        if not table.height:
            raise ResultsError(f"{original[0].req.results}: no row of run {original[1].run_id}, whose policy "
                               "other cells were to copy")
        written[place(original)] = table.row(0, named=True)
    return written[place(original)]


def _copy(copies: Sequence[Copy], written: dict[tuple[str, str], dict[str, Any]]) -> list[dict[str, Any]]:
    """Write the rows of `copies` (their originals' rows are at hand), each said in one line; their run folders get
    the original's projector."""
    made = []
    for (plan, cell), original in copies:
        row = _original_row(original, written)
        folder = plan.runs / row["run_id"] if isinstance(original, dict) else original[0].run_folder(original[1])
        trains = plan.control(cell).train
        kept = plan.copy_run_folder(cell, folder) if trains else False
        ignored = ", ".join(plan.control(cell).ignores)
        lost = f"; no projector in {folder}, so this run cannot be exported" if trains and not kept else ""
        plan.log(f"cell {cell.run_id} (seed {cell.seed} control {cell.control} cache {cell.cache_key}): same policy "
                 f"as run {row['run_id']} ({cell.control} ignores {ignored}): row copied, not refitted{lost}")
        made.append(plan.copied_row(cell, row))
    return _write([c for c, _ in copies], made)


def run_passes(plans: Sequence[Plan], runner: Runner,
               visited: Callable[[int], None] = lambda n: None) -> list[dict[str, Any]]:
    """Every missing cell of `plans`, pass by pass on `runner`, each row appended to its results file as its pass
    finishes; returns the rows written. `visited(n)`: n more cells were run or skipped.

    Other processes (fits, sweeps, here or on other machines, under any executor) may write the same results files:
    a cell is computed only under its claim (graftcache.results.claims.cell_claim), taken before its pass is submitted
    and given back once its row is written, so a cell another process is computing is left for later (its pass runs
    without it), then skipped once its row is in the file (or computed here if that process died).

    A missing cell whose policy is a run's already (`separate_copies`) is not fitted: its row is copied from that run's,
    at once when the results file holds it, else as soon as the cell of this command that fits it has its row."""
    set_main_threads()
    rows: list[dict[str, Any]] = []
    cells, copies = separate_copies(missing_cells(plans, visited))
    runner.to_run(cells)
    written: dict[tuple[str, str], dict[str, Any]] = {}  # (results file, run_id) -> the row this command wrote
    waiting: dict[tuple[str, str], list[Copy]] = {}  # a cell of this command -> the copies its row makes
    for copy in copies:
        if not isinstance(copy[1], dict):
            waiting.setdefault(place(copy[1]), []).append(copy)
    ready = [c for c in copies if isinstance(c[1], dict)]
    if ready:
        rows.extend(_copy(ready, written))
        visited(len(ready))
    claims = {place(c): cell_claim(*place(c)) for c in cells}
    left = Counter(id(plan) for plan, _ in cells)
    told: set[tuple[str, str]] = set()
    running: dict[int, list[Planned]] = {}  # ticket -> the pass's cells, their claims held

    def done(ps: Sequence[Planned]) -> None:
        visited(len(ps))
        for plan, _ in ps:
            left[id(plan)] -= 1
            if not left[id(plan)]:
                runner.finished(plan)  # its kept blocks and tables go before the next requests' are read

    def collect() -> None:
        ticket, got = runner.next_done()
        ps = running.pop(ticket)
        try:
            rows.extend(_write(ps, got))
        finally:
            release_all([claims[place(c)] for c in ps])
        written.update((place(c), row) for c, row in zip(ps, got, strict=True))
        done(ps)
        copy_waiting([place(c) for c in ps])

    def copy_waiting(at: Sequence[tuple[str, str]]) -> None:
        """The copies of the cells at `at`, whose rows are now in their files."""
        now = [c for a in at for c in waiting.pop(a, [])]
        if now:
            rows.extend(_copy(now, written))
            visited(len(now))

    try:
        while cells:
            busy = []
            for group in group_passes(cells):
                got = []
                try:
                    for plan, cell in group:
                        at = place((plan, cell))
                        if _take(claims[at]):
                            got.append((plan, cell))
                            continue
                        if at not in told:
                            plan.log(f"cell {cell.run_id} (seed {cell.seed} control {cell.control}) is being "
                                     f"computed by {claims[at].holder()}: waiting for its row")
                            told.add(at)
                        busy.append((plan, cell))
                    fresh = []
                    for plan, cell in got:  # another process may have written its row since
                        if cell.run_id in results.done_run_ids(plan.req.results):
                            plan.skipped([cell])
                        else:
                            fresh.append((plan, cell))
                    if fresh:
                        running[runner.submit(fresh)] = fresh
                except BaseException:
                    release_all([claims[place(c)] for c in got])
                    raise
                stale = [c for c in got if c not in fresh]
                release_all([claims[place(c)] for c in stale])
                done(stale)
                copy_waiting([place(c) for c in stale])
                while len(running) >= runner.slots:
                    collect()
            while running:
                collect()
            if busy:
                time.sleep(1.0)
            cells = busy
        copy_waiting(list(waiting))  # originals whose rows another process wrote
    finally:
        if running:
            runner.cancel()
            release_all([claims[place(c)] for ps in running.values() for c in ps])
        for path in {path for path, _ in claims}:
            drop_claims_folder(path)
    return rows
