#!/usr/bin/env python
"""The GPU truth in one command: what graftcache's CUDA paths compute and cost, stage by stage, in priority order.

    python benchmarks/gpu_check.py [--device cuda] [--budget-s 480] [--out FILE] [--stages 1,2,3,4,5,6]
    python benchmarks/gpu_check.py --tiny --device cpu      # the dry run CI runs (tests/test_gpu_check.py)

A GPU is lent now and then for minutes, so every stage writes its results into the JSON as it ends (device,
driver, torch, CUDA and the libraries named at the top) and a run cut short keeps what it measured. A stage that
would start past `--budget-s` is skipped and says so; an error in one check is recorded in one line and the next
check runs.

1. correctness, every backbone of graftcache.backbone_registry.BACKBONES at tiny size: graft; two cells in one pass
   (graftcache.graft.FusedProjector) for a few AdamW steps land on the projectors each cell reaches alone;
   every recompute plan gives the projector gradients plan off gives; predict in the compute dtype is
   finite; a tiny policy saved to disk and lean-loaded onto the device (graftcache.backbones.lean_load) predicts what
   the in-memory one predicts. Equality checks run in fp32 with TF32 off (what they test is the plumbing, not
   bf16 rounding); the compute-dtype step and predict are checked for finiteness.
2. pi0.5 at the released geometry, random-init and built on the device (devtools.released.on_device: meta ->
   device, no host copy, nothing downloaded): step seconds and peak device memory at each `--batches` with
   activation checkpointing off and on; the step's FLOPs (FlopCounterMode, counted once at the smallest batch:
   a step's FLOPs are linear in the batch) and MFU against the device's dense bf16 peak.
3. SmolVLA the same at `--smolvla-batches`, and `--cells-per-pass` 1, 2, 4 at the first of them: training cells
   per GPU-hour at cli/paper.toml's steps per cell.
4. pi0.5 (`--load-backbone`) lean load from a checkpoint on local disk (written from stage 2's weights, page
   cache dropped where the kernel allows), in a fresh process: seconds, host peak RSS against the checkpoint,
   whether the host ever held the model.
5. benchmarks/bench_protocol.py's measurements on cli/paper.toml with stage 2 and 3's backbones: projected
   GPU-hours of the paper's protocol from caches, online, and the FLOP bound at 100% and 40% MFU.
6. The other backbones devtools.released can build (pi0): one step at batch 8 (seconds, memory, MFU); the rest
   are listed as not buildable at released size here.
Issue 42's stages (the first a lent GPU runs: `--stages 7,8,9,10`):
7. pi0.5 at `--plan-batches` (8, 16, 32) x attention (eager, sdpa: FitRequest's `attention` setting) x recompute
   plan (off, mlp, on: graftcache.backbones.activation_checkpointing.PLANS): step seconds, peak memory, MFU (model
   FLOPs), each plan's estimate (graftcache.fit.step_bytes.frame_bytes), its recomputed FLOPs, and the plan `auto`
   takes at each batch on a `--card-gib` card.
8. SmolVLA at `--fused-batches` (stage 3's unless given) x attention x `--cells` per pass: training cells per
   GPU-hour.
9. Stage 5 again (`--card-backbones` of it) with the allocator capped at `--card-gib` (an 80 GB card on a larger
   GPU), fused attention where the backbone has it (`--attention auto`), each backbone's recompute plan found by
   `auto` under the cap.
10. `fit --compile` (graftcache.backbones.compiled) against eager, one cell of `--compile-backbones` at the first
   of its batches: compile seconds, step seconds, graphs and graph breaks, whether a pass's steps pay it back.
11. The closed loop (benchmarks/gpu_closed_loop.py): `graftcache rollout --workers N` of two tiny cells with the
   policy on the device and MuJoCo through EGL against the CPU path on the same episodes: episodes per hour, the
   renderer each arm got, rows compared (run with benchmarks/device/run_closed_loop.sh).

With `--tiny` every stage runs on the tiny backbones (stage 2-6's built through the same meta -> device path), so
the first GPU run cannot fail on a typo. Needs only the repository on PYTHONPATH beside lerobot 0.6.1, its
transformers pin and draccus/gymnasium (what the device image lacks travels as one bundle: benchmarks/device/README.md).
"""

from __future__ import annotations

import argparse
import contextlib
import gc
import json
import math
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
import traceback
from collections.abc import Callable, Iterator
from dataclasses import replace
from datetime import date
from pathlib import Path

os.environ.setdefault("HF_HUB_OFFLINE", "1")

import torch  # noqa: E402
from torch import nn  # noqa: E402
from torch.utils.flop_counter import FlopCounterMode  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "benchmarks")]

import bench_protocol as bp  # noqa: E402  (the GPU peaks, a sync, the protocol's measurements)
from gpu_closed_loop import stage_closed_loop  # noqa: E402

from devtools.released import CONFIGS, LIBERO, Recipe, built_on, on_device, unit_stats  # noqa: E402
from graftcache.backbone_registry import BACKBONES  # noqa: E402
from graftcache.backbones import load_backbone  # noqa: E402
from graftcache.backbones.compiled import compile_forward  # noqa: E402
from graftcache.backbones.patching import Patches  # noqa: E402
from graftcache.backbones.tiny import TinyBuild  # noqa: E402
from graftcache.fit.loop import Learner, alone, flow_time, optimise_together  # noqa: E402
from graftcache.fit.step_bytes import frame_bytes  # noqa: E402
from graftcache.graft import FusedProjector, GraftProjector, feature_key  # noqa: E402
from graftcache.runtime import autocast, resolve_compute_dtype, resolve_device, resolve_dtype  # noqa: E402

ENC_WIDTH = 768  # SigLIP-B's width: the graft's input in stages 2-6 (the cost hardly depends on it)
TINY_ENC = 48
TASK = "put the black bowl on the plate"
PAPER = ROOT / "cli" / "paper.toml"


# ---------------------------------------------------------------------------------------------- the report
class Report:
    """The JSON, rewritten after every check; `check` runs one named part, recording seconds, its results or
    its error in one line (plus the traceback's last lines), so nothing stops the stages after it."""

    def __init__(self, path: Path, budget_s: float, header: dict) -> None:
        self.path, self.budget_s, self.t0 = path, budget_s, time.perf_counter()
        self.data: dict = {"header": header, "budget_s": budget_s, "stages": {}}
        self.write()

    def elapsed(self) -> float:
        return time.perf_counter() - self.t0

    def left(self) -> float:
        return self.budget_s - self.elapsed()

    def write(self) -> None:
        self.data["elapsed_s"] = round(self.elapsed(), 1)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        tmp = self.path.with_suffix(".tmp")
        tmp.write_text(json.dumps(self.data, indent=1, default=str))
        tmp.replace(self.path)

    @contextlib.contextmanager
    def check(self, stage: str, name: str, need_s: float = 0.0) -> Iterator[dict | None]:
        """One check: yields the dict its results go in, or None (recorded as skipped) when fewer than `need_s`
        seconds of the budget are left."""
        entry: dict = {}
        self.data["stages"].setdefault(stage, {})[name] = entry
        if self.left() < need_s:
            entry.update(status="skipped", reason=f"budget: {self.left():.0f} s left, needs ~{need_s:.0f} s")
            self.write()
            print(f"[{self.elapsed():6.0f}s] {stage}/{name}: skipped (budget)", flush=True)
            yield None
            return
        t0 = time.perf_counter()
        try:
            yield entry
            entry.setdefault("status", "ok")
        except Exception as exc:  # recorded, and the next check runs
            entry.update(status="error", error=f"{type(exc).__name__}: {exc}".splitlines()[0][:400],
                         traceback=traceback.format_exc().splitlines()[-6:])
        entry["seconds"] = round(time.perf_counter() - t0, 2)
        self.write()
        shown = {k: v for k, v in entry.items() if k != "traceback"}
        print(f"[{self.elapsed():6.0f}s] {stage}/{name}: {json.dumps(shown, default=str)[:600]}", flush=True)


def header(device: torch.device, dtype_name: str) -> dict:
    """Where and with what this ran."""
    import importlib.metadata

    def version(name: str) -> str | None:
        try:
            return importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            return None

    cpu = next((ln.split(":", 1)[1].strip() for ln in Path("/proc/cpuinfo").read_text().splitlines()
                if ln.startswith("model name")), platform.processor())
    out = {"date": date.today().isoformat(), "device": str(device), "compute_dtype": dtype_name, "cpu": cpu,
           "cpu_avx512_bf16": "avx512_bf16" in Path("/proc/cpuinfo").read_text(), "cores": os.cpu_count(),
           "python": platform.python_version(), "torch": torch.__version__, "cuda": torch.version.cuda,
           **{name: version(name) for name in ("transformers", "lerobot", "tokenizers", "huggingface-hub",
                                                 "safetensors", "numpy")}}
    if device.type == "cuda":
        props = torch.cuda.get_device_properties(device)
        out.update(gpu=torch.cuda.get_device_name(device), gpu_memory_gb=round(props.total_memory / 1e9, 1),
                   sms=props.multi_processor_count)
        try:
            out["driver"] = subprocess.run(["nvidia-smi", "--query-gpu=driver_version", "--format=csv,noheader"],
                                           capture_output=True, text=True, timeout=20).stdout.strip()
        except (OSError, subprocess.SubprocessError) as exc:
            out["driver"] = f"unknown ({exc})"
    return out


def peak_flops(device: torch.device) -> tuple[float | None, str]:
    """The dense bf16 peak MFU is taken against, and where it comes from (None on a CPU: no MFU there)."""
    if device.type != "cuda":
        return None, "cpu: no peak (MFU is for GPUs)"
    name = torch.cuda.get_device_name(device)
    for key, tflops in bp.GPU_PEAKS.items():
        if key in name:
            return tflops * 1e12, f"{name}: {tflops:g} TFLOP/s dense bf16 (data sheet)"
    return None, f"{name}: no bf16 peak known"


def free(device: torch.device) -> None:
    """Collect cycles (a graft's instance overrides make policy and adapter one) and return cached blocks."""
    gc.collect()
    if device.type == "cuda":
        torch.cuda.empty_cache()


def peak_gb(device: torch.device) -> float | None:
    return round(torch.cuda.max_memory_allocated(device) / 1e9, 2) if device.type == "cuda" else None


def reset_peak(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)


@contextlib.contextmanager
def exact() -> Iterator[None]:
    """fp32 matmuls and convolutions without TF32, for the equality checks."""
    saved = torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32
    torch.backends.cuda.matmul.allow_tf32 = torch.backends.cudnn.allow_tf32 = False
    try:
        yield
    finally:
        torch.backends.cuda.matmul.allow_tf32, torch.backends.cudnn.allow_tf32 = saved


# ---------------------------------------------------------------------------------------------- batches
def tiny_recipe(tiny: TinyBuild) -> Recipe:
    return replace(LIBERO, cameras=tiny.cameras, state_dim=tiny.state_dim, action_dim=tiny.action_dim)


def features(adapter, frames: int, width: int, seed: int = 0) -> torch.Tensor:
    """Synthetic cached features [frames, tokens, width] at the backbone's token grid, fp16 like a cache."""
    g = torch.Generator().manual_seed(seed)
    tokens = adapter.token_grid[0] * adapter.token_grid[1]
    return torch.randn(frames, tokens, width, generator=g).half()


def step_features(adapter) -> torch.Tensor:
    """The 64 frames of features the timed steps draw from, at the graft's input width: SigLIP-B's (ENC_WIDTH) for a
    backbone of released size, the tiny encoder's for a tiny one."""
    return features(adapter, 64, ENC_WIDTH if adapter.tiny_marker is None else TINY_ENC)


def lowdim(adapter, batch: int, g: torch.Generator) -> dict:
    """Random raw state and action chunks, LIBERO's prompt (evaluation's batches carry the actions too)."""
    return {"observation.state": torch.randn(batch, adapter.state_dim, generator=g) * 0.5, "task": [TASK] * batch,
            "action": torch.randn(batch, adapter.chunk_size, adapter.action_dim, generator=g) * 0.5,
            "action_is_pad": torch.zeros(batch, adapter.chunk_size, dtype=torch.bool)}


def draw_from(adapter, feats: torch.Tensor, batch: int) -> Callable[[torch.Generator], dict]:
    """A Learner's draw: `batch` frames of `feats` for every camera, random state and action chunks."""
    def draw(g: torch.Generator) -> dict:
        pos = torch.randint(0, len(feats), (batch,), generator=g)
        return {**{feature_key(c): feats[pos].float() for c in adapter.cameras}, **lowdim(adapter, batch, g)}
    return draw


@contextlib.contextmanager
def no_dropout(policy: nn.Module) -> Iterator[None]:
    """Dropout off in training mode (the fit's step trains), so a batch of two draws no masks one sample would
    not: what the equality checks compare is the plumbing."""
    saved = {m: m.p for m in policy.modules() if isinstance(m, nn.modules.dropout._DropoutNd)}
    for m in saved:
        m.p = 0.0
    try:
        yield
    finally:
        for m, p in saved.items():
            m.p = p


def learners(adapter, projectors: list[nn.Module], feats: torch.Tensor, batch: int, seed0: int = 0,
             optimizer: Callable = lambda params: torch.optim.AdamW(params, lr=1e-3)) -> list[Learner]:
    """One Learner a projector (the fit's AdamW unless `optimizer` says otherwise), cell i seeded `seed0 + i`."""
    return [Learner(draw_from(adapter, feats, batch), optimizer(list(p.parameters())),
                    torch.Generator().manual_seed(seed0 + i)) for i, p in enumerate(projectors)]


def sgd(params: list[nn.Parameter]) -> torch.optim.Optimizer:
    """Plain SGD for the equality checks: a weight moves by lr x its gradient, so two runs differ by what their
    gradients differ (Adam's first steps move every weight by ~lr whatever its gradient's size, so a rounding
    difference in a near-zero gradient would become a whole step)."""
    return torch.optim.SGD(params, lr=1e-2)


def graft_cells(adapter, n: int, width: int, seed: int = 0) -> tuple[list[GraftProjector], Callable]:
    """Graft `n` fresh projectors (fused when n > 1): (projectors, the route of their rows)."""
    torch.manual_seed(seed)
    projectors = [GraftProjector(width, adapter.lm_width) for _ in range(n)]
    adapter.reset()
    if n == 1:
        adapter.graft(projectors[0])
        return projectors, alone
    fused = FusedProjector(projectors)
    adapter.graft(fused)
    return projectors, fused.rows


def max_rel(a: list[torch.Tensor], b: list[torch.Tensor]) -> float:
    """Largest |a - b| over all tensors, relative to the largest |b|."""
    diff = max(float((x.float() - y.float()).abs().max()) for x, y in zip(a, b, strict=True))
    scale = max(float(y.float().abs().max()) for y in b) or 1.0
    return diff / scale


# ---------------------------------------------------------------------------------------------- stage 1
def tiny_stats(tiny: TinyBuild) -> dict:
    return unit_stats(tiny_recipe(tiny))


def stage_tiny(report: Report, device: torch.device, dtype: torch.dtype, names: list[str]) -> None:
    """Correctness of every backbone at tiny size on the device."""
    tiny = TinyBuild()
    steps, batch = 3, 2
    for name in names:
        with report.check("1_tiny", name, need_s=15) as out:
            if out is None:
                continue
            adapter = load_backbone(name, "tiny", device=str(device), dataset_stats=tiny_stats(tiny), tiny=tiny)
            out["params"] = adapter.n_params
            feats = features(adapter, 16, TINY_ENC)
            with exact(), no_dropout(adapter.policy):
                out.update(fused_vs_solo(adapter, feats, steps, batch))
                out.update(checkpointing_gradients(adapter, feats, batch))
                out.update(lean_roundtrip(name, adapter, tiny, device))
            out.update(compute_dtype_step_and_predict(adapter, feats, batch, dtype))
            out["status"] = "ok" if all(v for k, v in out.items() if k.endswith("_ok")) else "failed"
            del adapter
            free(device)


def fused_vs_solo(adapter, feats: torch.Tensor, steps: int, batch: int) -> dict:
    """Two cells trained `steps` SGD steps in one pass against each alone: the projectors' weights after."""
    if not adapter.spec.loss_per_sample:
        return {"fused_ok": True, "fused": "not fusable (one loss a batch): cells run alone"}
    solo = []
    for i in range(2):
        (projector,), route = graft_cells(adapter, 1, feats.shape[-1], seed=i)
        optimise_together(adapter, learners(adapter, [projector], feats, batch, seed0=i, optimizer=sgd),
                          steps=steps, batch_size=batch, dtype=torch.float32, route=route, show=False)
        solo.extend(p.detach().clone() for p in projector.parameters())
    projectors, route = graft_cells(adapter, 2, feats.shape[-1], seed=0)
    torch.manual_seed(1)  # the second projector's initial weights as when it was made alone
    projectors[1].load_state_dict(GraftProjector(feats.shape[-1], adapter.lm_width).state_dict())
    cells = learners(adapter, projectors, feats, batch, optimizer=sgd)
    optimise_together(adapter, cells, steps=steps, batch_size=batch, dtype=torch.float32, route=route, show=False)
    fused = [p.detach().clone() for projector in projectors for p in projector.parameters()]
    adapter.reset()
    rel = max_rel(fused, solo)
    return {"fused_max_rel_diff": rel, "fused_ok": rel < 1e-4, "fused_losses": [c.final_loss for c in cells]}


def checkpointing_gradients(adapter, feats: torch.Tensor, batch: int) -> dict:
    """The projector's gradients of one loss under each recompute plan the backbone has against plan off."""
    if len(adapter.recompute_plans) == 1:
        return {"checkpointing_ok": True, "checkpointing": "not supported by this backbone"}
    (projector,), route = graft_cells(adapter, 1, feats.shape[-1])
    raw = draw_from(adapter, feats, batch)(torch.Generator().manual_seed(0))
    g = torch.Generator().manual_seed(1)
    noise, t = adapter.sample_noise(batch, generator=g), flow_time(batch, g).to(adapter.device)
    grads = {}
    adapter.policy.train()
    for plan in adapter.recompute_plans:
        adapter.set_recompute_plan(plan)
        projector.zero_grad(set_to_none=True)
        torch.manual_seed(0)  # the same dropout masks
        adapter.loss(adapter.prepare(raw), noise=noise, time=t).mean().backward()
        grads[plan] = [p.grad.detach().clone() for p in projector.parameters()]
    adapter.set_recompute_plan("off")
    adapter.reset()
    rel = max(max_rel(grads[plan], grads["off"]) for plan in adapter.recompute_plans[1:])
    return {"checkpointing_max_rel_diff": rel, "checkpointing_ok": rel < 1e-4,
            "plans_checked": list(adapter.recompute_plans[1:])}


def compute_dtype_step_and_predict(adapter, feats: torch.Tensor, batch: int, dtype: torch.dtype) -> dict:
    """A fused two-cell step and a predict in the compute dtype: finite, and the predicted chunk's shape."""
    n = 2 if adapter.spec.loss_per_sample else 1
    projectors, route = graft_cells(adapter, n, feats.shape[-1])
    cells = learners(adapter, projectors, feats, batch)
    optimise_together(adapter, cells, steps=2, batch_size=batch, dtype=dtype, route=route, show=False)
    raw = draw_from(adapter, feats, batch)(torch.Generator().manual_seed(0))
    adapter.policy.eval()
    noise = adapter.sample_noise(batch * n, generator=torch.Generator().manual_seed(2))
    both = {k: (v * n if isinstance(v, list) else torch.cat([v] * n)) for k, v in raw.items()}
    with torch.no_grad(), route([batch] * n), autocast(adapter.device, dtype):
        chunk = adapter.predict(adapter.prepare(both), noise=noise)
    adapter.reset()
    losses = [c.losses[-1] for c in cells]
    finite = all(torch.isfinite(torch.tensor(losses))) and bool(torch.isfinite(chunk).all())
    return {"compute_dtype_losses": losses, "predict_shape": list(chunk.shape), "compute_dtype_ok": finite}


def lean_roundtrip(name: str, adapter, tiny: TinyBuild, device: torch.device) -> dict:
    """The tiny policy saved to disk and lean-loaded onto the device: the same weights (sha256) and chunk."""
    from graftcache.backbone_registry import native_name
    from graftcache.encoders import load_encoder

    adapter.reset()
    with tempfile.TemporaryDirectory(prefix="gpu-check-") as tmp:
        adapter.save(Path(tmp) / name)
        t0 = time.perf_counter()
        loaded = load_backbone(name, Path(tmp) / name, device=str(device))
        seconds = time.perf_counter() - t0
        native = load_encoder(native_name(name), policy=str(Path(tmp) / name), device=device)  # no host copy
        native_on = sorted({p.device.type for p in native.adapter.policy.parameters()})
        del native
    images = {k: torch.rand(2, 3, 128, 128, generator=torch.Generator().manual_seed(3)) for k in adapter.camera_keys}
    raw = {**images, **lowdim(adapter, 2, torch.Generator().manual_seed(0))}
    chunks = []
    for a in (adapter, loaded):
        a.policy.eval()
        noise = a.sample_noise(2, generator=torch.Generator().manual_seed(4))
        with torch.no_grad():
            chunks.append(a.predict(a.prepare(dict(raw)), noise=noise))
    same_weights = loaded.policy_sha256 == adapter.policy_sha256
    on_device = {p.device.type for p in loaded.policy.parameters()} == {device.type}
    rel = max_rel([chunks[1]], [chunks[0]])
    del loaded
    return {"lean_load_s": round(seconds, 2), "lean_same_sha256": same_weights, "lean_chunk_max_rel_diff": rel,
            "native_encoder_on": native_on, "lean_ok": same_weights and on_device and rel < 1e-4,
            "native_ok": native_on == [device.type]}


# ---------------------------------------------------------------------------------------------- stages 2, 3, 6
def built(name: str, device: torch.device, tiny: bool, hub: Path):
    """Backbone `name` random-init on `device` through meta -> device: at the released geometry, or (`--tiny`) at
    the tiny one (lerobot's constructor at the tiny marker's sizes)."""
    if not tiny:
        return on_device(name, device, cache=hub)
    tiny = TinyBuild()
    base = load_backbone(name, "tiny", device="cpu", dataset_stats=tiny_stats(tiny), tiny=tiny)
    return built_on(type(base), base.policy.config, device, tiny_stats(tiny), source=f"tiny {name} on {device}",
                    marker=base.tiny_marker)


def step_flops(adapter, feats: torch.Tensor, batch: int, dtype: torch.dtype, plan: str = "off") -> int:
    """FLOPs of one training step of one cell at `batch` under recompute plan `plan` (off: model FLOPs, no
    recomputation; another plan's count includes what it recomputes in backward)."""
    (projector,), route = graft_cells(adapter, 1, feats.shape[-1])
    adapter.set_recompute_plan(plan)
    with FlopCounterMode(display=False) as counter:
        optimise_together(adapter, learners(adapter, [projector], feats, batch), steps=1, batch_size=batch,
                          dtype=dtype, route=route, show=False)
    bp.sync(adapter.device)
    adapter.set_recompute_plan("off")
    return counter.get_total_flops()


def time_step(adapter, feats: torch.Tensor, batch: int, dtype: torch.dtype, cells: int, repeats: int,
              plan: str, compile_backend: str | None = None) -> dict:
    """Median seconds of one step of `cells` fused cells at `batch` each under recompute plan `plan`, and the peak
    device memory; an out-of-memory step is recorded as such (and its memory released outside the except block,
    where the traceback no longer holds the step's activations). `compile_backend`: the training forward compiled
    with it (graftcache.backbones.compiled), the warm-up step's seconds (its compilation) recorded as `first_step_s`."""
    device = adapter.device
    projectors, route = graft_cells(adapter, cells, feats.shape[-1])
    adapter.set_recompute_plan(plan)
    compiled = compile_forward(adapter, compile_backend) if compile_backend else Patches()
    group = learners(adapter, projectors, feats, batch)
    bp.sync(device)
    base = torch.cuda.memory_allocated(device) if device.type == "cuda" else None
    reset_peak(device)
    times: list[float] = []
    oom = None
    try:
        for _ in range(repeats + 1):
            t0 = time.perf_counter()
            optimise_together(adapter, group, steps=1, batch_size=batch, dtype=dtype, route=route, show=False)
            bp.sync(device)
            times.append(time.perf_counter() - t0)
    except torch.OutOfMemoryError as exc:
        oom = str(exc).splitlines()[0][:200]
    finally:
        compiled.undo()
    out = {"batch": batch, "cells": cells, "plan": plan, "checkpointing": plan != "off", "peak_gb": peak_gb(device)}
    if oom is None:
        out["loss_finite"] = all(math.isfinite(x) for cell in group for x in cell.losses)
    if base is not None:  # what the step adds to the weights (and optimiser state) already there
        out["step_peak_gb"] = round(out["peak_gb"] - base / 1e9, 2)
    del group, projectors
    adapter.reset()
    adapter.set_recompute_plan("off")
    free(device)
    if oom is not None:
        return {**out, "oom": oom}
    return {**out, "step_s": statistics.median(times[1:]), "first_step_s": times[0]}


def step_estimate(adapter, feats: torch.Tensor, dtype: torch.dtype, plan: str) -> dict:
    """What graftcache.fit.step_memory measures before a fit under recompute plan `plan`
    (graftcache.fit.step_bytes.frame_bytes): on CUDA the allocator's peak of a 1- and a 2-frame step, elsewhere
    the bytes autograd saves (a lower bound)."""
    graft_cells(adapter, 1, feats.shape[-1])
    adapter.set_recompute_plan(plan)
    one, per_frame = frame_bytes(adapter, lambda f: draw_from(adapter, feats, f)(torch.Generator().manual_seed(0)),
                                 dtype)
    adapter.reset()
    adapter.set_recompute_plan("off")
    free(adapter.device)
    basis = "cuda allocator peak" if adapter.device.type == "cuda" else "autograd saved bytes (a lower bound)"
    return {"one_frame_gb": one / 1e9, "per_frame_gb": per_frame / 1e9, "basis": basis}


def scaling(report: Report, stage: str, adapter, batches: list[int], dtype: torch.dtype, repeats: int,
            peak: float | None) -> None:
    """Step time and memory against batch, checkpointing off and on, with FLOPs and MFU."""
    feats = step_features(adapter)
    with report.check(stage, "flops", need_s=20) as out:
        if out is not None:
            flops = step_flops(adapter, feats, batches[0], dtype)
            out.update(batch=batches[0], step_flops=flops, flops_per_sample=flops / batches[0])
    per_sample = report.data["stages"][stage]["flops"].get("flops_per_sample")
    for ckpt in ("off", "on"):
        if ckpt not in adapter.recompute_plans:
            continue
        with report.check(stage, f"estimate_ckpt_{ckpt}", need_s=15) as out:
            if out is not None:
                out.update(step_estimate(adapter, feats, dtype, ckpt))
        rule = report.data["stages"][stage][f"estimate_ckpt_{ckpt}"]
        for batch in batches:
            key = f"batch{batch}_ckpt_{ckpt}"
            with report.check(stage, key, need_s=25) as out:
                if out is None:
                    continue
                out.update(time_step(adapter, feats, batch, dtype, 1, repeats, ckpt))
                if adapter.device.type == "cuda" and "one_frame_gb" in rule:  # step_memory's CUDA rule vs the peak
                    out["estimate_gb"] = round(rule["one_frame_gb"] + (batch - 1) * rule["per_frame_gb"], 2)
                if "step_s" in out and per_sample:
                    achieved = per_sample * batch / out["step_s"]
                    out["tflops"] = round(achieved / 1e12, 1)
                    out["mfu"] = round(achieved / peak, 4) if peak else None
                if "oom" in out:
                    out["status"] = "oom"
            if out is not None and "oom" in out:
                break  # larger batches would not fit either


def record_cells(out: dict, result: dict, n: int, steps_per_cell: int, **also: str) -> None:
    """Put one timed step of `n` cells (time_step's `result`) into a check's `out`, with `also`: its seconds a
    cell-step and training cells per GPU-hour at `steps_per_cell`, or status oom where no step ran."""
    out.update(result, **also)
    if "step_s" in result:
        cell_step = result["step_s"] / n
        out.update(cell_step_s=cell_step, steps_per_cell=steps_per_cell,
                   training_cells_per_gpu_hour=3600 / (steps_per_cell * cell_step))
    else:
        out["status"] = "oom"


def cells_per_pass(report: Report, stage: str, adapter, batch: int, counts: list[int], dtype: torch.dtype,
                   repeats: int, steps_per_cell: int) -> None:
    """Seconds a cell-step against cells per pass at `batch`, and training cells per GPU-hour at
    `steps_per_cell` (recompute on only where off does not fit)."""
    feats = step_features(adapter)
    for n in counts:
        with report.check(stage, f"cells_per_pass_{n}", need_s=30) as out:
            if out is None:
                continue
            if n > 1 and not adapter.spec.loss_per_sample:
                out.update(status="skipped", reason="one loss a batch: cells run alone")
                continue
            result = time_step(adapter, feats, batch, dtype, n, repeats, "off")
            if "oom" in result and adapter.spec.can_recompute:
                result = time_step(adapter, feats, batch, dtype, n, repeats, "on")
            record_cells(out, result, n, steps_per_cell)


# ---------------------------------------------------------------------------------------------- stages 7-10
#: The attention paths stages 7 and 8 compare (FitRequest's `attention` setting, graftcache.backbones.attention).
ATTENTIONS = ("eager", "sdpa")


def plan_estimates(adapter, feats: torch.Tensor, batch: int, dtype: torch.dtype) -> dict:
    """Per recompute plan: what graftcache.fit.step_memory measures (a 1-frame step's bytes and each further frame's)
    and a step's FLOPs at `batch` (what it recomputes: `recompute_fraction` of the plain step's); the plans ranked by
    per-frame bytes, most first, which must be their order of recompute."""
    out: dict = {}
    for plan in adapter.recompute_plans:
        estimate = step_estimate(adapter, feats, dtype, plan)
        out[plan] = {**estimate, "step_flops": step_flops(adapter, feats, batch, dtype, plan)}
    base = out["off"]["step_flops"]
    for plan in adapter.recompute_plans:
        out[plan]["recompute_fraction"] = out[plan]["step_flops"] / base - 1
    by_bytes = sorted(adapter.recompute_plans, key=lambda plan: -out[plan]["per_frame_gb"])
    by_flops = sorted(adapter.recompute_plans, key=lambda plan: out[plan]["step_flops"])
    out.update(batch=batch, by_per_frame_bytes=by_bytes, by_recompute=by_flops,
               ranked_ok=by_bytes == by_flops == list(adapter.recompute_plans))
    return out


def first_plan_that_fits(estimates: dict, plans: tuple[str, ...], batch: int, have_gb: float) -> str | None:
    """What `--recompute auto` picks at `batch` where `have_gb` is free: the first plan whose
    estimated step fits (None: none does)."""
    return next((plan for plan in plans
                 if estimates[plan]["one_frame_gb"] + (batch - 1) * estimates[plan]["per_frame_gb"] <= have_gb), None)


def plans_and_attention(report: Report, stage: str, adapter, batches: list[int], dtype: torch.dtype, repeats: int,
                        peak: float | None, card_gb: float) -> None:
    """Stage 7: step seconds, peak memory and MFU at each batch, attention path and recompute plan, with each plan's
    estimate, and which plan `auto` takes at each batch on a card of `card_gb` (the weights already on it)."""
    feats = step_features(adapter)
    weights_gb = torch.cuda.memory_allocated(adapter.device) / 1e9 if adapter.device.type == "cuda" else 0.0
    for attention in ATTENTIONS:
        with report.check(stage, f"estimate_{attention}", need_s=30) as out:
            if out is None:
                continue
            adapter.set_attention(attention)
            estimates = plan_estimates(adapter, feats, batches[0], dtype)
            out.update(estimates, attention=attention, card_gb=card_gb, weights_gb=weights_gb,
                       auto_on_card={f"batch{b}": first_plan_that_fits(estimates, adapter.recompute_plans, b,
                                                                       card_gb - weights_gb) for b in batches})
        estimates = report.data["stages"][stage][f"estimate_{attention}"]
        if estimates.get("status") != "ok":
            continue
        per_sample = estimates["off"]["step_flops"] / batches[0]  # model FLOPs: what a plan recomputes is not in MFU
        for batch in batches:
            for plan in adapter.recompute_plans:
                with report.check(stage, f"batch{batch}_{attention}_{plan}", need_s=25) as out:
                    if out is None:
                        continue
                    out.update(time_step(adapter, feats, batch, dtype, 1, repeats, plan), attention=attention)
                    out["estimate_gb"] = round(estimates[plan]["one_frame_gb"]
                                               + (batch - 1) * estimates[plan]["per_frame_gb"], 4)
                    if "step_s" in out:
                        achieved = per_sample * batch / out["step_s"]
                        out.update(tflops=round(achieved / 1e12, 3), mfu=round(achieved / peak, 4) if peak else None)
                    else:
                        out["status"] = "oom"
    adapter.set_attention("eager")


def fused_cells(report: Report, stage: str, adapter, batches: list[int], counts: list[int], dtype: torch.dtype,
                repeats: int, steps_per_cell: int) -> None:
    """Stage 8: cell-step seconds at each attention path, batch and cells per pass, and training cells per
    GPU-hour at `steps_per_cell` (the first of the backbone's recompute plans whose step does not run out of memory)."""
    feats = step_features(adapter)
    for attention in ATTENTIONS:
        for batch in batches:
            for n in counts:
                with report.check(stage, f"{attention}_batch{batch}_cells{n}", need_s=30) as out:
                    if out is None:
                        continue
                    adapter.set_attention(attention)
                    result: dict = {}
                    for plan in adapter.recompute_plans:
                        result = time_step(adapter, feats, batch, dtype, n, repeats, plan)
                        if "oom" not in result:
                            break
                    record_cells(out, result, n, steps_per_cell, attention=attention)
    adapter.set_attention("eager")


def compile_pays(report: Report, stage: str, adapter, batch: int, cells: int, dtype: torch.dtype, repeats: int,
                 steps_per_cell: int, backend: str) -> None:
    """Stage 10: `fit --compile` (graftcache.backbones.compiled) against the eager step at `batch` x `cells`: the
    compilation's seconds (the compiled warm-up step's beyond a compiled step), the seconds it saves a step, and
    whether a cell's steps (`steps_per_cell`, shared by the pass's cells) pay it back."""
    feats = step_features(adapter)
    with report.check(stage, f"{adapter.name}_batch{batch}_cells{cells}", need_s=120) as out:
        if out is None:
            return
        plan = "off"
        eager = time_step(adapter, feats, batch, dtype, cells, repeats, plan)
        if "oom" in eager:  # the plan that keeps least, as a fit that does not fit would
            plan = adapter.recompute_plans[-1]
            eager = time_step(adapter, feats, batch, dtype, cells, repeats, plan)
        torch._dynamo.reset()  # a compilation of its own, not one an earlier check left cached
        counters = torch._dynamo.utils.counters
        counters.clear()
        compiled = time_step(adapter, feats, batch, dtype, cells, repeats, plan, compile_backend=backend)
        out.update(graphs=counters["stats"]["unique_graphs"], graph_breaks=sum(counters["graph_break"].values()))
        compile_s = compiled["first_step_s"] - compiled["step_s"]
        saved = eager["step_s"] - compiled["step_s"]
        steps = steps_per_cell  # the cells of a pass train their steps together: a pass runs steps_per_cell steps
        out.update(backend=backend, plan=plan, batch=batch, cells=cells, eager_step_s=eager["step_s"],
                   compiled_step_s=compiled["step_s"], compile_s=compile_s, saved_s_per_step=saved,
                   steps_to_pay_back=compile_s / saved if saved > 0 else None, steps_per_pass=steps,
                   pays_within_a_pass=saved > 0 and compile_s < saved * steps,
                   eager_peak_gb=eager["peak_gb"], compiled_peak_gb=compiled["peak_gb"])


@contextlib.contextmanager
def card_of(device: torch.device, card_gib: float) -> Iterator[str]:
    """The CUDA allocator capped at `card_gib` (torch.cuda.set_per_process_memory_fraction) for the block, so a
    larger GPU runs as a card of that size would (its compute and bandwidth stay the larger one's); says what it did."""
    if device.type != "cuda":
        yield "cpu: no device memory to cap"
        return
    total = torch.cuda.get_device_properties(device).total_memory
    fraction = min(1.0, card_gib * 2**30 / total)
    torch.cuda.set_per_process_memory_fraction(fraction, device)
    try:
        yield f"allocator capped at {card_gib:g} GiB ({fraction:.3f} of {total / 2**30:.1f} GiB)"
    finally:
        torch.cuda.set_per_process_memory_fraction(1.0, device)


# ---------------------------------------------------------------------------------------------- stage 4
LOAD_SCRIPT = r"""
import json, os, sys, time
from pathlib import Path
sys.path[:0] = [sys.argv[3]]
def rss(field):
    return next(int(l.split()[1]) * 1024 for l in Path('/proc/self/status').read_text().splitlines()
                if l.startswith(field + ':'))
t0 = time.perf_counter()
import torch
from graftcache.backbones import get_backbone, load_backbone
from lerobot.policies.factory import get_policy_class
get_backbone(sys.argv[1]); get_policy_class(sys.argv[1])
imported = time.perf_counter() - t0
try:
    Path('/proc/self/clear_refs').write_text('5')
    cleared = True
except OSError:
    cleared = False
before = rss('VmRSS')
t0 = time.perf_counter()
adapter = load_backbone(sys.argv[1], Path(sys.argv[2]), device=sys.argv[4])
seconds = time.perf_counter() - t0
dev = torch.device(sys.argv[4])
print(json.dumps({'import_s': imported, 'load_s': seconds, 'rss_before_gb': before / 1e9,
                  'peak_rss_gb': rss('VmHWM') / 1e9, 'peak_reset_before_load': cleared,
                  'rss_after_gb': rss('VmRSS') / 1e9,
                  'device_gb': torch.cuda.memory_allocated(dev) / 1e9 if dev.type == 'cuda' else None,
                  'params_on': sorted({p.device.type for p in adapter.policy.parameters()})}))
"""


def save_checkpoint(adapter, folder: Path) -> dict:
    """Write the ungrafted policy as lerobot writes it (config, model.safetensors, processors)."""
    adapter.reset()
    t0 = time.perf_counter()
    adapter.save(folder)
    size = (folder / "model.safetensors").stat().st_size
    return {"save_s": round(time.perf_counter() - t0, 1), "checkpoint_gb": round(size / 1e9, 2)}


def save(report: Report, adapter, folder: Path) -> None:
    with report.check("4_lean_load", "save", need_s=60) as info:
        if info is not None:
            info.update(backbone=adapter.name, **save_checkpoint(adapter, folder))


def drop_page_cache() -> bool:
    """Ask the kernel to drop clean pages (root only), so the load reads the disk; whether it did."""
    try:
        os.sync()
        Path("/proc/sys/vm/drop_caches").write_text("3")
        return True
    except OSError:
        return False


def lean_load(name: str, folder: Path, device: torch.device, hub: Path) -> dict:
    """Lean-load the checkpoint in a fresh process (the hub repos its processors read in `hub`): seconds, host
    peak RSS against the checkpoint's bytes."""
    dropped = drop_page_cache()
    env = {**os.environ, "HF_HUB_OFFLINE": "1", "HF_HUB_CACHE": str(hub)}
    done = subprocess.run([sys.executable, "-c", LOAD_SCRIPT, name, str(folder), str(ROOT), str(device)],
                          capture_output=True, text=True, env=env, timeout=600)
    if done.returncode != 0:
        raise RuntimeError(f"load process exited {done.returncode}: {done.stderr.strip().splitlines()[-1:]}")
    out = json.loads(done.stdout.strip().splitlines()[-1])
    checkpoint = (folder / "model.safetensors").stat().st_size / 1e9
    growth = out["peak_rss_gb"] - out["rss_before_gb"]
    return {**out, "page_cache_dropped": dropped, "checkpoint_gb": round(checkpoint, 2),
            "host_peak_growth_gb": round(growth, 2),
            "host_held_model": growth > 0.5 * checkpoint if device.type == "cuda" else "cpu target"}


# ---------------------------------------------------------------------------------------------- stage 5
def protocol(report: Report, adapters: dict, device: torch.device, dtype: torch.dtype, dtype_name: str,
             peak: float | None, tiny: bool, encoders: list[str] | None, stage: str = "5_protocol",
             attention: str = "eager", backbones: list[str] | None = None) -> None:
    """bench_protocol's per-kind measurements on cli/paper.toml (or its `backbones` alone) with these adapters on
    attention path `attention`, and its projection."""
    with report.check(stage, "recipe", need_s=60) as out:
        if out is None:
            return
        from graftcache.encoders import load_encoder
        from graftcache.recipe import load_recipe

        recipe = load_recipe(PAPER)
        if encoders:  # a subset of the recipe's encoders (the CPU dry run's, to stay short)
            unknown = sorted(set(encoders) - {e.name for e in recipe.encoders})
            if unknown:
                raise ValueError(f"--encoders {', '.join(unknown)}: not in {PAPER.relative_to(ROOT)}")
            recipe = replace(recipe, encoders=tuple(e for e in recipe.encoders if e.name in encoders))
        if backbones:  # a subset of the recipe's backbones (stage 9 in the CPU dry run, to stay short)
            unknown = sorted(set(backbones) - {b.name for b in recipe.backbones})
            if unknown:
                raise ValueError(f"--card-backbones {', '.join(unknown)}: not in {PAPER.relative_to(ROOT)}")
            recipe = replace(recipe, backbones=tuple(b for b in recipe.backbones if b.name in backbones))
        settings = bp.recipe_settings(recipe, 2 if tiny else None)
        resolved = {b.name: adapters[b.name].set_attention(attention) for b in recipe.backbones if b.name in adapters}
        out.update(recipe=str(PAPER.relative_to(ROOT)), encoders=[e.name for e in recipe.encoders],
                   settings=settings.__dict__, attention=attention, attention_resolved=resolved)
    if out.get("status") != "ok":
        return
    a = argparse.Namespace(steps=2 if tiny else 4, eval_frames=2 if tiny else 32)
    encode_s: dict[str, float] = {}
    for entry in recipe.encoders:
        with report.check(stage, f"encoder_{entry.name}", need_s=15) as out:
            if out is None:
                return
            encoder = load_encoder(entry.name, random_init=True, device=device)
            encode_s[entry.name] = bp.encode_seconds_per_image(encoder.forward_grid, encoder.spec.image_size,
                                                               settings.batch_size, device, dtype)
            out["encode_s_per_image"] = encode_s[entry.name]
            del encoder
    measured: dict[str, dict] = {}
    tower_s, cameras = {}, {}
    for entry in recipe.backbones:
        adapter = adapters.get(entry.name)
        if adapter is None:
            report.data["stages"][stage][entry.name] = {"status": "skipped", "reason": "not built in this run"}
            return
        adapter.reset()
        side = LIBERO.image_size
        cameras[entry.name] = len(adapter.cameras)
        tower_s[entry.name] = bp.encode_seconds_per_image(adapter.native_tokens, side, settings.batch_size, device,
                                                          dtype)
        native_width = adapter.native_patch_grid(torch.zeros(1, 3, side, side)).shape[-1]
        by_kind: dict = {}
        measured[entry.name] = {}
        for cell, kind in bp.kinds_of(recipe, entry.name, adapter, native_width).items():
            if kind not in by_kind:
                name = f"{entry.name}_{kind.tokens}x{kind.width}{'_lora' if kind.lora else ''}" + (
                    "" if kind.train else "_eval") + ("_native" if kind.native_tower else "")
                with report.check(stage, name, need_s=30) as out:
                    if out is None:
                        return
                    out.update({**kind.__dict__, **bp.measure_kind(adapter, kind, settings, a, dtype)})
                by_kind[kind] = out
                adapter.reset()
                adapter.set_recompute_plan("off")
                free(device)  # each kind starts from the weights alone, as a sweep's cell does
            measured[entry.name][cell] = by_kind[kind]
        adapter.reset()
        free(device)
    failed = sorted({k for per in measured.values() for k, m in per.items() if m.get("status") != "ok"}, key=str)
    with report.check(stage, "projection") as out:
        if out is None:
            return
        if failed:
            out.update(status="skipped", reason=f"{len(failed)} cell kinds were not measured: {failed[:3]}")
            return
        decode = report.data["header"].get("decode_s_per_frame") or 0.0
        hours = bp.project(recipe, settings, measured, {n: 0.0 for n in measured}, decode, encode_s, tower_s,
                           cameras, peak or bp.peak_flops(device, dtype, None)[0])
        out.update(hours, rows=sum(1 for _ in bp.cells(recipe)) * len(recipe.seeds),
                   settings=settings.__dict__, decode_s_per_frame=decode,
                   notes="loads excluded (stage 4 times one); online hours exclude video decoding unless "
                         "--decode-ms is given (no PyAV on the device image): a lower bound")
    for adapter in adapters.values():
        adapter.set_attention("eager")


# ---------------------------------------------------------------------------------------------- main
def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--device", default="cuda")
    p.add_argument("--compute-dtype", default="auto", choices=("auto", "bf16", "fp32"))
    p.add_argument("--tiny", action="store_true", help="tiny backbones everywhere (the CPU dry run)")
    p.add_argument("--budget-s", type=float, default=480.0, help="no stage starts past this many seconds")
    p.add_argument("--stages", default="1,2,3,4,5,6,7,8,9,10,11",
                   help="comma list; issue 42's are 7 (pi0.5 attention x recompute plans), 8 (SmolVLA attention x "
                   "cells per pass), 9 (the protocol on an 80 GB card), 10 (torch.compile against eager); 11 is the "
                   "closed loop (benchmarks/gpu_closed_loop.py)")
    p.add_argument("--backbones", default=",".join(BACKBONES), help="stage 1's backbones")
    p.add_argument("--batches", default=None, help="stage 2's batches (default 8,16,32,64; tiny 2,4)")
    p.add_argument("--smolvla-batches", default=None, help="stage 3's batches (default 32,64; tiny 2,4)")
    p.add_argument("--plan-batches", default=None, help="stage 7's batches (default 8,16,32; tiny 2,4)")
    p.add_argument("--fused-batches", default=None, help="stage 8's batches (default stage 3's)")
    p.add_argument("--cells", default="1,2,4", help="stage 8's cells per pass")
    p.add_argument("--card-gib", type=float, default=79.1,
                   help="stages 7 and 9: the card to fit (default an 80 GB H100's memory as torch reports it)")
    p.add_argument("--card-backbones", default=None,
                   help="stage 9's backbones of the recipe (default all; the CPU dry run: one, to stay short)")
    p.add_argument("--compile-backbones", default="pi05,smolvla", help="stage 10's backbones (one cell each)")
    p.add_argument("--compile-backend", default="inductor",
                   help="stage 10's torch.compile backend (the CPU dry run in CI: eager, dynamo's capture alone, to "
                   "stay short; tests/backbones/test_compiled.py checks aot_eager's numbers)")
    p.add_argument("--repeats", type=int, default=3, help="timed steps per measurement, after one warm-up")
    p.add_argument("--load-backbone", default="pi05", choices=("pi05", "smolvla"),
                   help="stage 4's checkpoint (smolvla: a released-size dry run a CPU can afford)")
    p.add_argument("--encoders", default=None, help="stage 5: only these of cli/paper.toml's encoders (comma list)")
    p.add_argument("--decode-ms", type=float, default=None,
                   help="video decode per frame (a CPU measurement) for stage 5's online protocol")
    p.add_argument("--scratch", type=Path, default=None, help="local disk for stage 4's checkpoint and the hub")
    p.add_argument("--closed-loop-cells", type=Path, default=None,
                   help="stage 11's cells, a folder benchmarks/closed_loop_cells.py wrote (default: fitted into "
                   "--scratch first, which needs the data layer a GPU image lacks)")
    p.add_argument("--closed-loop-workers", default=None,
                   help="stage 11's worker counts (default: the machine's cores; tiny 2)")
    p.add_argument("--closed-loop-episodes", type=int, default=None,
                   help="stage 11's episodes per cell (default: the most workers; tiny 1)")
    p.add_argument("--closed-loop-steps", type=int, default=None,
                   help="stage 11's steps per episode (default 40, the closed-loop demo's; tiny 3)")
    p.add_argument("--cpu-gl", default="egl",
                   help="stage 11's CPU path's MUJOCO_GL (default egl: Mesa's on a CPU machine; where only the "
                   "GPU's EGL is installed it renders there, which the arm's renderer says)")
    p.add_argument("--device-gl", default="egl", help="stage 11's device path's MUJOCO_GL (default egl)")
    p.add_argument("--out", type=Path, default=None,
                   help="JSON (default benchmarks/results/gpu_check_<gpu>_<date>.json)")
    a = p.parse_args(argv)
    stages = {int(s) for s in a.stages.split(",") if s}
    device = resolve_device(a.device)
    dtype_name = resolve_compute_dtype(a.compute_dtype, device)
    dtype = resolve_dtype(dtype_name)
    batches = [int(b) for b in (a.batches or ("2,4" if a.tiny else "8,16,32,64")).split(",")]
    smol_batches = [int(b) for b in (a.smolvla_batches or ("2,4" if a.tiny else "32,64")).split(",")]
    plan_batches = [int(b) for b in (a.plan_batches or ("2,4" if a.tiny else "8,16,32")).split(",")]
    fused_batches = [int(b) for b in a.fused_batches.split(",")] if a.fused_batches else smol_batches
    cells = [int(n) for n in a.cells.split(",")]
    head = header(device, dtype_name)
    head.update(tiny=a.tiny, decode_s_per_frame=None if a.decode_ms is None else a.decode_ms / 1e3,
                random_init=True, note="every policy here is random-init: costs, not what weights learned")
    peak, head["peak_source"] = peak_flops(device)
    slug = "".join(c if c.isalnum() else "-" for c in (head.get("gpu") or device.type).lower())
    out = a.out or ROOT / "benchmarks" / "results" / f"gpu_check_{slug}_{head['date']}{'_tiny' if a.tiny else ''}.json"
    report = Report(out, a.budget_s, head)
    print(f"gpu_check: {json.dumps(head)} -> {out}", flush=True)
    scratch = Path(a.scratch or tempfile.mkdtemp(prefix="gpu-check-"))
    hub = scratch / "hub"
    from graftcache.recipe import load_recipe

    steps_per_cell = int(load_recipe(PAPER).fit["steps"])  # what one cell of the paper's protocol trains

    if 1 in stages:
        stage_tiny(report, device, dtype, [n for n in a.backbones.split(",") if n])
    adapters: dict = {}
    load_name = a.load_backbone
    if stages & {2, 5, 7, 9, 10} or (4 in stages and load_name == "pi05"):
        with report.check("2_pi05", "build", need_s=30) as info:
            if info is not None:
                adapters["pi05"] = built("pi05", device, a.tiny, hub)
                info.update(params=adapters["pi05"].n_params, source=adapters["pi05"].source,
                            device_gb=peak_gb(device))
    if 7 in stages and "pi05" in adapters:
        plans_and_attention(report, "7_pi05_plans", adapters["pi05"], plan_batches, dtype, a.repeats, peak,
                            a.card_gib * 2**30 / 1e9)
    if 2 in stages and "pi05" in adapters:
        scaling(report, "2_pi05", adapters["pi05"], batches, dtype, a.repeats, peak)
    if 4 in stages and load_name in adapters:
        save(report, adapters[load_name], scratch / load_name)
    if stages & {3, 5, 8, 9, 10} or (4 in stages and load_name == "smolvla"):
        with report.check("3_smolvla", "build", need_s=20) as info:
            if info is not None:
                adapters["smolvla"] = built("smolvla", device, a.tiny, hub)
                info.update(params=adapters["smolvla"].n_params, source=adapters["smolvla"].source)
    if 4 in stages and load_name == "smolvla" and "smolvla" in adapters:
        save(report, adapters["smolvla"], scratch / "smolvla")
    if 8 in stages and "smolvla" in adapters:
        fused_cells(report, "8_smolvla_fused", adapters["smolvla"], fused_batches, cells, dtype, a.repeats,
                    steps_per_cell)
    if 10 in stages:
        for name, batch in (("pi05", plan_batches[0]), ("smolvla", smol_batches[0])):
            if name in adapters and name in a.compile_backbones.split(","):
                compile_pays(report, "10_compile", adapters[name], batch, 1, dtype, a.repeats, steps_per_cell,
                             a.compile_backend)
    if 3 in stages and "smolvla" in adapters:
        scaling(report, "3_smolvla", adapters["smolvla"], smol_batches, dtype, a.repeats, peak)
        cells_per_pass(report, "3_smolvla", adapters["smolvla"], smol_batches[0], [1, 2, 4], dtype, a.repeats,
                       steps_per_cell)
    if 4 in stages and (scratch / load_name / "model.safetensors").is_file():
        with report.check("4_lean_load", "load", need_s=60) as info:
            if info is not None:
                info.update(backbone=load_name, **lean_load(load_name, scratch / load_name, device, hub))
    encoders = [e for e in a.encoders.split(",") if e] if a.encoders else None
    if 5 in stages:
        protocol(report, adapters, device, dtype, dtype_name, peak, a.tiny, encoders)
    if 9 in stages:  # the fused path where the backbone has it, each backbone's plan as auto finds it under the cap
        with card_of(device, a.card_gib) as cap:
            report.data["stages"]["9_protocol_80gb"] = {"card": {
                "status": "ok", "card_gib": a.card_gib, "cap": cap, "attention": "auto"}}
            protocol(report, adapters, device, dtype, dtype_name, peak, a.tiny, encoders, stage="9_protocol_80gb",
                     attention="auto", backbones=[b for b in a.card_backbones.split(",") if b] if a.card_backbones
                     else None)
    adapters.clear()
    free(device)
    if 6 in stages:
        for name in BACKBONES:
            if name in ("pi05", "smolvla"):
                continue
            if name not in CONFIGS:
                report.data["stages"].setdefault("6_zoo", {})[name] = {
                    "status": "skipped", "reason": "no released-geometry builder in devtools.released yet"}
                continue
            with report.check("6_zoo", name, need_s=60) as info:
                if info is None:
                    continue
                adapter = built(name, device, a.tiny, hub)
                info["params"] = adapter.n_params
                width = TINY_ENC if a.tiny else ENC_WIDTH
                feats = features(adapter, 64, width)
                batch = 2 if a.tiny else 8
                flops = step_flops(adapter, feats, batch, dtype)
                info.update(time_step(adapter, feats, batch, dtype, 1, a.repeats, "off"), step_flops=flops)
                if "step_s" in info:
                    info["tflops"] = round(flops / info["step_s"] / 1e12, 1)
                    info["mfu"] = round(flops / info["step_s"] / peak, 4) if peak else None
                del adapter
                free(device)
        report.write()
    if 11 in stages:
        most = os.cpu_count() or 1
        workers = [int(n) for n in (a.closed_loop_workers or ("2" if a.tiny else str(most))).split(",")]
        stage_closed_loop(report, a.device, a.closed_loop_cells, scratch, workers,
                          a.closed_loop_episodes or (1 if a.tiny else max(workers)),
                          a.closed_loop_steps or (3 if a.tiny else 40), a.cpu_gl, a.device_gl)
    report.data["done"] = True
    report.write()
    print(f"gpu_check: done in {report.elapsed():.0f} s -> {out}", flush=True)
    return report.data


if __name__ == "__main__":
    main()
