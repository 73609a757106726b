"""Running cells: a pass of 1..N cells of one pass key (graftcache.fit.plan.Plan.pass_key), top to bottom, one row each.

A pass grafts its cells' projectors (one cell: its projector; several: a graftcache.graft.FusedProjector, each
cell on its own rows of every batch), fits them through the cells' objective (graftcache.fit.objectives.OBJECTIVES;
the flow steps of several cells in one forward and backward), scores them together, saves each projector in its
run folder and returns each cell's row. The single cell is the case of one: there is one training path.

The policy is loaded once per process and reset to its pristine state between passes (graft surgery mutates it),
and fitted from cached features only. What a pass reads comes from each cell's request's Materials
(graftcache/fit/materials.py); which cells exist, are finished or share a pass, from its Plan (graftcache/fit/plan.py,
nothing loaded); the claims and the results file, from graftcache.fit.passes.run_passes, whichever executor runs
the passes (`LocalRunner` here; Ray tasks: graftcache/executors/ray_fit.py).

The parts a cell is made of are registries: its control (fit/controls.py: which cache, which projector,
which feature transform) and its objective (fit/objectives.py: how the projector is fitted).
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Mapping, Sequence
from contextlib import ExitStack, closing
from dataclasses import asdict
from pathlib import Path
from typing import Any

import torch
from safetensors.torch import save_file

import graftcache
from graftcache import results
from graftcache.backbones.base import BackboneAdapter
from graftcache.backbones.checkpoint import follow_umask
from graftcache.backbones.compiled import compile_forward
from graftcache.backbones.loaded import LoadedBackbones
from graftcache.backbones.patching import Patches
from graftcache.cameras import format_camera_map
from graftcache.encoders.fingerprint import NumericsCheck
from graftcache.fit.data import Split
from graftcache.fit.loop import Scoring, alone, evaluate_together
from graftcache.fit.materials import Materials, MaterialsOf, Reading
from graftcache.fit.objectives import Fitting
from graftcache.fit.passes import Member, run_passes
from graftcache.fit.plan import Cell, Plan
from graftcache.fit.step_memory import check_step_memory
from graftcache.fit.stream import StreamStats, read_blocks
from graftcache.graft import FusedProjector
from graftcache.pooling import format_grid
from graftcache.requests import FitRequest
from graftcache.store.readthrough import ReadThroughRoot

__all__ = ["Cell", "FitRequest", "Fitter", "LocalRunner", "run_pass"]

PROJECTOR_WEIGHTS = "projector.safetensors"  # in a cell's run folder: its trained parameters
PROJECTOR_SIDECAR = "projector.json"         # beside them: its cell, split and freeze report (save_projector)


def run_pass(members: Sequence[Member], materials: MaterialsOf) -> list[dict[str, Any]]:
    """Fit and score the cells of one pass (one cell, or several of one pass key: `plan_passes`) and return their
    rows in order, without writing them (graftcache.fit.passes.run_passes writes them, under the cells' claims)."""
    mats = [materials(m.plan) for m in members]
    for mat in mats:
        mat.check_numerics()
    first, plan, req = mats[0], members[0].plan, members[0].plan.req
    adapter = first.backbone()
    reads = [mat.reading(adapter, m.control) for m, mat in zip(members, mats, strict=True)]
    objective = plan.objective_of(members[0].control)  # one for every cell of a pass (their pass key says so)
    t0 = time.perf_counter()
    projectors = []
    for m, reading in zip(members, reads, strict=True):
        torch.manual_seed(m.cell.seed)  # each projector starts where it starts alone
        projectors.append(m.control.projector(reading.width, adapter.lm_width))
    one = len(members) == 1
    grafted = projectors[0] if one else FusedProjector(projectors)
    adapter.graft(grafted)
    if one and members[0].control.lora:
        adapter.add_lora(rank=req.lora_rank)
    route = alone if one else grafted.rows
    # measuring a step (step_memory) feeds the first cell's rows only: the others' projectors get none
    measuring = alone if one else lambda sizes: grafted.rows([*sizes, *[0] * (len(members) - len(sizes))])
    first.backbones.describe(adapter, _pass_name(members, reads))
    adapter.set_memory_plan("off")  # only a training step uses a plan (what the last pass left)
    if members[0].control.train and objective.scheduled:  # refused here, not OOM-killed later
        check_step_memory(adapter, reads[0].train, plan.cameras, reads[0].source, batch_size=req.batch_size,
                          buffer_mib=req.buffer_mib, dtype=first.dtype, checkpointing=req.activation_checkpointing,
                          others=[(r.train, r.source, m.plan.req.buffer_mib)
                                  for m, r in zip(members[1:], reads[1:], strict=True)],
                          route=measuring)
    checkpointing = adapter.memory_plan
    trainables = _trainables(adapter, grafted, projectors)
    stats = [StreamStats() for _ in members]
    # --compile: the training forward compiled for this pass's steps; scoring and the next pass run eagerly
    compiled = compile_forward(adapter) if req.compile and objective.scheduled else Patches()
    try:
        losses = objective.fit([
            Fitting(adapter=adapter, req=m.plan.req, control=m.control, params=list(trainable.values()),
                    train=mat.feed(r, r.train, m.control, m.seed), cams=m.plan.cameras,
                    targets=(r.targets, r.target_rows) if r.targets is not None else None, grid=r.grid, seed=m.seed,
                    dtype=mat.dtype, stats=st)
            for m, mat, r, trainable, st in zip(members, mats, reads, trainables, stats, strict=True)], route)
    finally:
        compiled.undo()
    t_eval = time.perf_counter()
    with ExitStack() as stack:
        scores = evaluate_together(adapter, [
            Scoring(r.eval, stack.enter_context(closing(read_blocks(
                mat.feed(r, r.eval, m.control, m.seed + 1).features(seed=None), m.plan.req.num_workers, st))),
                m.plan.cameras, m.control.transform)
            for m, mat, r, st in zip(members, mats, reads, stats, strict=True)],
            batch_size=req.eval_batch_size, dtype=first.dtype, num_denoise_steps=req.num_denoise_steps, route=route)
    eval_share = (time.perf_counter() - t_eval) / len(members)
    share = (time.perf_counter() - t0) / len(members)
    rows = []
    for m, mat, r, trainable, loss, score, st in zip(members, mats, reads, trainables, losses, scores, stats,
                                                     strict=True):
        if m.control.train:
            save_projector(m.plan.run_folder(m.cell), adapter, m.cell, m.plan.split, trainable)
        rows.append(_told(m, _row(m, mat, adapter, r, loss, score, st, share, cells=len(members),
                                  checkpointing=checkpointing, eval_s=eval_share)))
    return rows


def _pass_name(members: Sequence[Member], reads: Sequence[Reading]) -> str:
    """How the log names a pass when the table of what trains is printed."""
    if len(members) == 1:
        (m,), (r,) = members, reads
        return f"cell {m.cell.run_id} ({r.encoder} seed {m.seed} control {m.control.name})"
    return (f"the {len(members)} cells of a backbone pass, each training its own projector "
            f"({', '.join(m.cell.run_id for m in members)})")


def _trainables(adapter: BackboneAdapter, grafted: torch.nn.Module,
                projectors: Sequence[torch.nn.Module]) -> list[dict[str, torch.nn.Parameter]]:
    """Each cell's trained parameters, named as in the policy: alone, every trainable one (its projector, LoRA's);
    in a pass of several, its own projector's under the fused projector's name."""
    if len(projectors) == 1:
        return [{n: p for n, p in adapter.policy.named_parameters() if p.requires_grad}]
    prefix = next(name for name, module in adapter.policy.named_modules() if module is grafted)
    return [{f"{prefix}.{n}": p for n, p in projector.named_parameters()} for projector in projectors]


def _row(m: Member, mat: Materials, adapter: BackboneAdapter, r: Reading, loss: float, score, stats: StreamStats,
         wall: float, *, cells: int, checkpointing: str, eval_s: float) -> dict[str, Any]:
    """A cell's row from what it measured (`cells`: how many cells its backbone pass trained; `checkpointing`:
    the memory plan the step ran under; `eval_s`: its scoring's seconds, its share of a pass's)."""
    plan = m.plan
    if isinstance(plan.root, ReadThroughRoot):  # what the reading processes copied locally for this cell
        plan.root.fetched_bytes += stats.fetched
    return m.cell.row(plan.req, {
        "run_id": m.cell.run_id, "format_version": results.FORMAT_VERSION, "policy_sha256": adapter.policy_sha256,
        "encoder": r.encoder,
        "pool_grid": format_grid(r.grid), "train_loss_final": loss, "eval_mse": score.mse,
        "eval_mse_first": score.mse_first, "eval_mse_raw": score.mse_raw, "eval_mse_arm": score.mse_arm,
        "eval_mse_gripper": score.mse_gripper,
        "eval_mse_episodes": [score.per_episode[e] for e in sorted(score.per_episode)],
        "eval_ci_mse": score.ci_mse,
        "eval_ci_mse_episodes": [score.ci_per_episode[e] for e in sorted(score.per_episode)],
        "backbone_params": adapter.n_params,
        "n_eval_frames": score.n_frames, "n_eval_episodes": len(score.per_episode), "wall_s": wall,
        "cells_per_pass": cells, "device": str(plan.device),
        "random_init": bool(r.cache.manifest.random_init or adapter.random_init),
        "encoder_random_init": bool(r.cache.manifest.random_init),
        "backbone_random_init": bool(adapter.random_init),
        "n_dropped_nonfinite": r.dropped + len(stats.dropped), "numerics_drift": mat.drift(r),
        "camera_map": format_camera_map(plan.cameras), "graftcache_version": graftcache.__version__,
        "activation_checkpointing": checkpointing, "eval_seconds_per_frame": eval_s / score.n_frames,
    })


def _told(m: Member, row: dict[str, Any]) -> dict[str, Any]:
    """`row`, once its scores are in the log."""
    shared = f" (its share of a pass of {row['cells_per_pass']})" if row["cells_per_pass"] > 1 else ""
    m.plan.log(f"{row['backbone']}/{row['encoder']}/{row['suite']} seed {row['seed']} control {m.control.name} "
               f"(cell {row['run_id']}): eval_mse {row['eval_mse']:.4f} (first {row['eval_mse_first']:.4f}, raw "
               f"{row['eval_mse_raw']:.5f}) on {row['n_eval_frames']} frames "
               f"({row['eval_seconds_per_frame'] * 1e3:.1f} ms a frame at --eval-batch-size "
               f"{row['eval_batch_size']}), {row['wall_s']:.1f}s{shared}; activation checkpointing "
               f"{row['activation_checkpointing']}")
    return row


def save_projector(folder: Path, adapter: BackboneAdapter, cell: Cell, split: Split,
                   trainable: Mapping[str, torch.Tensor]) -> None:
    """A cell's trained parameters, named as in the policy, with a JSON sidecar (its cell, split, freeze report)."""
    folder.mkdir(parents=True, exist_ok=True)
    save_file({n: p.detach().cpu().contiguous() for n, p in trainable.items()}, str(folder / PROJECTOR_WEIGHTS))
    follow_umask(folder / PROJECTOR_WEIGHTS)
    sidecar = {"run_id": cell.run_id, "cell": asdict(cell), "split": asdict(split),
               "freeze": str(adapter.freeze_report()), "graftcache_version": graftcache.__version__}
    (folder / PROJECTOR_SIDECAR).write_text(json.dumps(sidecar, indent=2, default=str))


def saved_cell(folder: Path) -> Cell | None:
    """The Cell save_projector recorded in `folder`'s sidecar (None: a sidecar without one)."""
    recorded = json.loads((folder / PROJECTOR_SIDECAR).read_text()).get("cell")
    return None if recorded is None else Cell(**recorded)


class LocalRunner:
    """Passes in this process, one at a time (graftcache.fit.passes.Runner), each request's Materials made on its
    first pass and dropped once it has no cell left; the backbones and numerics verdicts are shared by all."""

    slots = 1

    def __init__(self, backbones: LoadedBackbones, numerics: dict[str, NumericsCheck] | None = None) -> None:
        self.backbones = backbones
        self.numerics = {} if numerics is None else numerics
        self._materials: dict[int, Materials] = {}  # id(plan) -> its materials
        self._queue: list[tuple[int, Sequence[Member]]] = []
        self._tickets = 0

    def materials(self, plan: Plan) -> Materials:
        if id(plan) not in self._materials:
            self._materials[id(plan)] = Materials(plan, self.backbones, self.numerics)
        return self._materials[id(plan)]

    def planned(self, members: Sequence[Member]) -> None:
        """Nothing to say: each pass's rows are told as they come."""

    def submit(self, members: Sequence[Member]) -> int:
        self._tickets += 1
        self._queue.append((self._tickets, members))
        return self._tickets

    def next_done(self) -> tuple[int, list[dict[str, Any]]]:
        ticket, members = self._queue.pop(0)
        return ticket, run_pass(members, self.materials)

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

    @property
    def req(self) -> FitRequest:
        return self.plan.req

    @property
    def root(self) -> Any:  # the cache root as read (a ReadThroughRoot counts what it copied)
        return self.plan.root

    @property
    def index(self) -> Any:
        return self.plan.index

    def cells(self) -> list[tuple[Any, int, Cell]]:
        return self.plan.cells()

    def run_folder(self, cell: Cell) -> Path:
        return self.plan.run_folder(cell)

    def run(self) -> list[dict[str, Any]]:
        """Every missing cell, `cells_per_pass` cells to a pass of the backbone where they can share one
        (graftcache/fit/passes.py), each row appended to the results file as its pass finishes."""
        return run_passes([self.plan], self.runner)
