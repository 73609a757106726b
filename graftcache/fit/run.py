"""Running cells: a pass of 1..N cells of one pass key (graftcache.fit.plan.Plan.pass_key), top to bottom, one row each.

A pass grafts its cells' projectors (one cell: its projector; several: a graftcache.graft.FusedProjector, each
cell on its own rows of every batch), fits them through the cells' objective (graftcache.fit.objectives.OBJECTIVES;
the flow steps of several cells in one forward and backward), scores them together, saves each projector in its
run folder and returns each cell's row. The single cell is the case of one: there is one training path.

The policy is loaded once per process and reset to its pristine state between passes (graft surgery mutates it),
and fitted from cached features only. What a pass reads comes from each cell's request's Materials
(graftcache/fit/materials.py); which cells exist, are finished or share a pass, from its Plan (graftcache/fit/plan.py,
nothing loaded); the claims and the results file, from graftcache.fit.passes.run_passes, whichever executor runs
the passes (graftcache.fit.local.LocalRunner in this process; Ray tasks: graftcache/executors/ray_fit.py).

The parts a cell is made of are registries: its control (fit/controls.py: which cache, which projector,
which feature transform) and its objective (fit/objectives.py: how the projector is fitted).
"""

from __future__ import annotations

import json
import time
from collections.abc import Mapping, Sequence
from contextlib import ExitStack, closing
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import torch
from safetensors.torch import save_file

import graftcache
from graftcache import results
from graftcache.backbones.base import BackboneAdapter
from graftcache.backbones.checkpoint import follow_umask
from graftcache.backbones.compiled import compile_forward
from graftcache.backbones.patching import Patches
from graftcache.cameras import format_camera_map
from graftcache.fit.controls import Control
from graftcache.fit.data import Split
from graftcache.fit.dose import Seen
from graftcache.fit.loop import Scoring, alone, evaluate_together
from graftcache.fit.materials import Materials, MaterialsOf, Reading
from graftcache.fit.objectives import Fitting
from graftcache.fit.plan import PROJECTOR_SIDECAR, PROJECTOR_WEIGHTS, Cell, Plan, Planned
from graftcache.fit.step_memory import check_step_memory
from graftcache.fit.stream import StreamStats, read_blocks
from graftcache.graft import FusedProjector
from graftcache.requests import FitRequest
from graftcache.runtime import kernels
from graftcache.store.readthrough import ReadThroughRoot

__all__ = ["PROJECTOR_SIDECAR", "PROJECTOR_WEIGHTS", "Cell", "FitRequest", "run_pass", "save_projector",
           "saved_cell"]



@dataclass
class _InPass:
    """One cell of a pass and what the pass made for it: the one record of a cell inside `run_pass`."""

    plan: Plan
    cell: Cell
    control: Control
    mat: Materials
    read: Reading
    projector: torch.nn.Module
    seen: Seen                      # what its policy sees of a batch (its control's transform, its dose)
    trainable: dict[str, torch.nn.Parameter] = field(default_factory=dict)
    stats: StreamStats = field(default_factory=StreamStats)

    def fitting(self, adapter: BackboneAdapter) -> Fitting:
        """What the cell's objective fits it from."""
        r, seed = self.read, self.cell.seed
        return Fitting(adapter=adapter, req=self.plan.req, control=self.control, seen=self.seen,
                       params=list(self.trainable.values()),
                       train=self.mat.feed(r, r.train, self.control, seed), cams=self.plan.cameras,
                       targets=(r.targets, r.target_rows) if r.targets is not None else None, grid=r.grid, seed=seed,
                       dtype=self.mat.dtype, stats=self.stats)

    def scoring(self, stack: ExitStack) -> Scoring:
        """What scores the cell: its held-out split, streamed until `stack` closes."""
        r = self.read
        blocks = read_blocks(self.mat.feed(r, r.eval, self.control, self.cell.seed + 1).features(seed=None),
                             self.plan.req.num_workers, self.stats)
        return Scoring(r.eval, stack.enter_context(closing(blocks)), self.plan.cameras, self.seen)


def run_pass(cells: Sequence[Planned], materials: MaterialsOf) -> list[dict[str, Any]]:
    """Fit and score the cells of one pass (one cell, or several of one pass key: graftcache.fit.passes.group_passes)
    and return their rows in order, without writing them (graftcache.fit.passes.run_passes writes them, under the
    cells' claims)."""
    mats = [materials(plan) for plan, _ in cells]
    for mat in mats:
        mat.check_numerics()
    first, (plan, _) = mats[0], cells[0]
    req = plan.req
    adapter = first.backbone()
    ins = []
    for (p, cell), mat in zip(cells, mats, strict=True):
        control = p.control(cell)
        torch.manual_seed(cell.seed)  # each projector starts where it starts alone
        read = mat.reading(adapter, control)
        ins.append(_InPass(p, cell, control, mat, read, control.projector(p.width(control), adapter.lm_width),
                           mat.seen(read, control, cell.seed)))
    lead = ins[0]
    objective = plan.objective_of(lead.control)  # one for every cell of a pass (their pass key says so)
    t0 = time.perf_counter()
    one = len(ins) == 1
    grafted = lead.projector if one else FusedProjector([c.projector for c in ins])
    adapter.graft(grafted)
    if one and lead.control.lora:
        adapter.add_lora(rank=req.lora_rank)
    route = alone if one else grafted.rows
    # measuring a step (step_memory) feeds the first cell's rows only: the others' projectors get none
    measuring = alone if one else lambda sizes: grafted.rows([*sizes, *[0] * (len(ins) - len(sizes))])
    first.backbones.describe(adapter, _pass_name(ins))
    adapter.set_recompute_plan("off")  # only a training step uses a plan (what the last pass left)
    attention = adapter.set_attention(req.attention)  # before the step is measured: it changes what a step keeps
    if lead.control.train and objective.scheduled:  # refused here, not OOM-killed later
        check_step_memory(adapter, lead.read.train, plan.cameras, lead.read.source, batch_size=req.batch_size,
                          buffer_mib=req.buffer_mib, dtype=first.dtype, recompute=req.recompute,
                          others=[(c.read.train, c.read.source, c.plan.req.buffer_mib) for c in ins[1:]],
                          route=measuring)
    recomputed = adapter.recompute_plan
    for c, trainable in zip(ins, _trainables(adapter, grafted, [c.projector for c in ins]), strict=True):
        c.trainable = trainable
    # --compile: the training forward compiled for this pass's steps; scoring and the next pass run eagerly
    compiled = compile_forward(adapter) if req.compile and objective.scheduled else Patches()
    try:
        losses = objective.fit([c.fitting(adapter) for c in ins], route)
    finally:
        compiled.undo()
    t_eval = time.perf_counter()
    with ExitStack() as stack:
        scores = evaluate_together(adapter, [c.scoring(stack) for c in ins], batch_size=req.eval_batch_size,
                                   dtype=first.dtype, num_denoise_steps=req.num_denoise_steps, route=route)
    eval_share = (time.perf_counter() - t_eval) / len(ins)
    share = (time.perf_counter() - t0) / len(ins)
    rows = []
    for c, loss, score in zip(ins, losses, scores, strict=True):
        if c.control.train:
            save_projector(c.plan.run_folder(c.cell), adapter, c.cell, c.plan.split, c.trainable)
        if c.seen.dose is not None:  # the spread its noise was scaled by, for its export
            c.seen.dose.save(c.plan.run_folder(c.cell))
        rows.append(_told(c, _row(c, adapter, loss, score, share, cells=len(ins), recomputed=recomputed,
                                  attention=attention, eval_s=eval_share)))
    return rows


def _pass_name(ins: Sequence[_InPass]) -> str:
    """How the log names a pass when its freeze report (what trains) is logged."""
    if len(ins) == 1:
        (c,) = ins
        return f"cell {c.cell.run_id} ({c.read.encoder} seed {c.cell.seed} control {c.cell.control})"
    return (f"the {len(ins)} cells of a backbone pass, each training its own projector "
            f"({', '.join(c.cell.run_id for c in ins)})")


def _trainables(adapter: BackboneAdapter, grafted: torch.nn.Module,
                projectors: Sequence[torch.nn.Module]) -> list[dict[str, torch.nn.Parameter]]:
    """Each cell's trained parameters, named as in the policy: alone, every trainable one (its projector, LoRA's);
    in a pass of several, its own projector's under the fused projector's name."""
    if len(projectors) == 1:
        return [{n: p for n, p in adapter.policy.named_parameters() if p.requires_grad}]
    prefix = next(name for name, module in adapter.policy.named_modules() if module is grafted)
    return [{f"{prefix}.{n}": p for n, p in projector.named_parameters()} for projector in projectors]


def _row(c: _InPass, adapter: BackboneAdapter, loss: float, score: Any, wall: float, *, cells: int,
         recomputed: str, attention: str, eval_s: float) -> dict[str, Any]:
    """A cell's row from what it measured (`cells`: how many cells its backbone pass trained; `recomputed`: the
    recompute plan the step ran under; `attention`: the path the frozen LM and expert attended with; `eval_s`: its
    scoring's seconds, its share of a pass's)."""
    plan, r = c.plan, c.read
    if isinstance(plan.root, ReadThroughRoot):  # what the reading processes copied locally for this cell
        plan.root.fetched_bytes += c.stats.fetched
    return c.cell.row(plan.req, {  # pool_grid: the cell's (graftcache.fit.plan.Plan.grid), which its run_id hashes
        "run_id": c.cell.run_id, "policy_id": plan.policy_id(c.cell), "format_version": results.FORMAT_VERSION,
        "policy_sha256": adapter.policy_sha256,
        "encoder": r.encoder, "train_loss_final": loss, "eval_mse": score.mse,
        "eval_mse_first": score.mse_first, "eval_mse_raw": score.mse_raw, "eval_mse_arm": score.mse_arm,
        "eval_mse_gripper": score.mse_gripper,
        "eval_mse_episodes": [score.per_episode[e] for e in sorted(score.per_episode)],
        "eval_ci_mse": score.ci_mse,
        "eval_ci_mse_episodes": [score.ci_per_episode[e] for e in sorted(score.per_episode)],
        "backbone_params": adapter.n_params,
        "n_eval_frames": score.n_frames, "n_eval_episodes": len(score.per_episode), "wall_s": wall,
        "cells_per_pass": cells, "device": str(plan.device),
        "random_init": r.cache.manifest.unreleased or bool(adapter.random_init),
        "encoder_random_init": r.cache.manifest.unreleased,
        "backbone_random_init": bool(adapter.random_init),
        "n_dropped_nonfinite": r.dropped + len(c.stats.dropped), "numerics_drift": c.mat.drift(r),
        "camera_map": format_camera_map(plan.cameras), "graftcache_version": graftcache.__version__,
        "activation_checkpointing": recomputed, "eval_seconds_per_frame": eval_s / score.n_frames,
        "attention": attention, "kernels": kernels(plan.device),
    })


def _told(c: _InPass, row: dict[str, Any]) -> dict[str, Any]:
    """`row`, once its scores are in the log."""
    shared = f" (its share of a pass of {row['cells_per_pass']})" if row["cells_per_pass"] > 1 else ""
    c.plan.log(f"{row['backbone']}/{row['encoder']}/{row['suite']} seed {row['seed']} control {c.control.name} "
               f"(cell {row['run_id']}): eval_mse {row['eval_mse']:.4f} (first {row['eval_mse_first']:.4f}, raw "
               f"{row['eval_mse_raw']:.5f}) on {row['n_eval_frames']} frames "
               f"({row['eval_seconds_per_frame'] * 1e3:.1f} ms a frame at --eval-batch-size "
               f"{row['eval_batch_size']}), {row['wall_s']:.1f}s{shared}; recompute "
               f"{row['activation_checkpointing']}, {row['attention']} attention")
    return row


def save_projector(folder: Path, adapter: BackboneAdapter, cell: Cell, split: Split,
                   trainable: Mapping[str, torch.Tensor]) -> None:
    """A cell's trained parameters, named as in the policy, with a JSON sidecar (its cell, split, freeze report, and
    the policy's folder as an absolute path: the cell names the policy as given, `fit --policy P` relative to the
    folder the fit ran in, and keeps that name, which its run_id hashes; `export` reads the folder from here)."""
    folder.mkdir(parents=True, exist_ok=True)
    save_file({n: p.detach().cpu().contiguous() for n, p in trainable.items()}, str(folder / PROJECTOR_WEIGHTS))
    follow_umask(folder / PROJECTOR_WEIGHTS)
    loaded = Path(adapter.source)
    sidecar = {"run_id": cell.run_id, "cell": asdict(cell), "policy_folder": str(loaded.resolve()) if loaded.is_dir()
               else None, "split": asdict(split),
               "freeze": str(adapter.freeze_report()), "graftcache_version": graftcache.__version__}
    (folder / PROJECTOR_SIDECAR).write_text(json.dumps(sidecar, indent=2, default=str))


def saved_policy_folder(folder: Path) -> str | None:
    """The absolute policy folder save_projector recorded in `folder`'s sidecar (None: a hub id, or a sidecar written
    before it was recorded)."""
    return json.loads((folder / PROJECTOR_SIDECAR).read_text()).get("policy_folder")


def saved_cell(folder: Path) -> Cell | None:
    """The Cell save_projector recorded in `folder`'s sidecar (None: a sidecar without one). A sidecar written before
    results format 5 recorded the identity's version among the cell's fields (`format_version`:
    results.IDENTITY_VERSION), which the run_id hashes anyway; one of another version is no cell of this graftcache's
    (None)."""
    recorded = json.loads((folder / PROJECTOR_SIDECAR).read_text()).get("cell")
    if recorded is None or recorded.pop("format_version", results.IDENTITY_VERSION) != results.IDENTITY_VERSION:
        return None
    return Cell(**recorded)
