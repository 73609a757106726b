#!/usr/bin/env python
"""What a recipe's protocol costs: projected device-hours of `graftcache sweep RECIPE` from cached features,
beside the same protocol run online and beside the FLOP bound.

    python benchmarks/bench_protocol.py [--recipe cli/paper.toml] [--device cuda] [--compute-dtype auto]
        [--steps 24] [--eval-frames 128] [--tiny] [--batch-size N] [--hub DIR] [--out FILE]

Backbones are the recipe's at the released geometry, random-init (devtools.released, written into
`--hub` and loaded by hub id as `--policy org/name` loads them; the cost does not depend on what the weights
learned), or with `--tiny` the tiny configurations (a CPU smoke test: CI runs it). Features are synthetic, in
memory, fp16 like a cache, at each encoder's true width (its registry spec) and at the grid each cell reads
(the backbone's token grid, a pool control's grid; the native controls: the native tower's widths): pooling
runs in the fit's reading workers, off the device. For every distinct cell kind (backbone, tokens, width,
LoRA, trained or not) it measures:
- `--steps` flow steps (graftcache.fit.loop.optimise, the fit's own step), under the recipe's recompute plan
  (`auto`: the backbone's plans, least recompute first, until a step does not run out of device memory);
- scoring of `--eval-frames` held-out frames at the recipe's eval batch size and denoising steps;
- the FLOPs of one step and of one scoring batch (torch.utils.flop_counter.FlopCounterMode), counted on the
  untimed warm-up.
Then, over the recipe's cells (backbones x suites x seeds x encoders x controls; native-cache controls once per
backbone, suite and seed, as `sweep` runs them) and lerobot/libero's held-out frames per suite
(devtools.libero_counts.LIBERO_COUNTS x eval_fraction, capped by the recipe's eval_frames):
- cached protocol = loads (one per backbone, as a sweep's LoadedBackbones) + training + evaluation; stage 1
  (decoding and encoding every frame once per encoder) is printed beside it, not in the sum;
- online protocol = loads + the same steps and scoring with every batch's frames decoded (the project's own
  decoder, graftcache.datasets, at its sequential rate on `--dataset`: a lower bound for random access) and
  encoded (the encoder's forward at random init; the native controls: the policy's own tower) first;
- FLOP bound = the protocol's counted FLOPs at 100% and at 40% of the device's peak (bf16 dense, named in the
  JSON: a table of GPUs; on a CPU, a measured 2048^3 matmul in the compute dtype, or `--peak-tflops`).
JSON into benchmarks/results/ (or `--out`), naming the device and the CPU.
"""

from __future__ import annotations

import argparse
import contextlib
import gc
import json
import os
import re
import time
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, replace
from pathlib import Path

os.environ.setdefault("HF_HUB_OFFLINE", "1")

import numpy as np
import torch
from common import DEFAULT_DATASET, machine
from torch.utils.flop_counter import FlopCounterMode

from devtools.libero_counts import LIBERO_COUNTS
from devtools.released import BUILDERS, LIBERO, built_here, hub_cache, unit_stats
from graftcache.backbones import load_backbone
from graftcache.backbones.tiny import TinyBuild
from graftcache.encoders import load_encoder
from graftcache.encoders.registry import get_spec
from graftcache.fit.controls import get_control
from graftcache.fit.loop import optimise
from graftcache.graft import GraftProjector, feature_key
from graftcache.recipe import Recipe, load_recipe
from graftcache.requests import FitRequest
from graftcache.runtime import (
    autocast,
    resolve_compute_dtype,
    resolve_device,
    resolve_dtype,
    set_main_threads,
)
from graftcache.scoring import frame_noise

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_HUB = Path.home() / ".cache" / "graftcache" / "bench-real-size-hub"
#: Dense bf16 tensor-core peaks (TFLOP/s, no sparsity) from the vendors' data sheets, by device-name substring.
GPU_PEAKS = {"H200": 989.0, "H100": 989.0, "A100": 312.0, "L40S": 362.0, "L4": 121.0, "A10": 125.0, "4090": 165.0}
POOL_FRAMES = 64  # distinct synthetic frames batches are drawn from


@dataclass(frozen=True)
class Kind:
    """What a cell's step and scoring cost depends on."""

    backbone: str
    tokens: int        # per camera, as the cell reads them
    width: int         # feature width
    lora: bool
    train: bool
    native_tower: bool  # online, the policy's own tower makes its features (native controls)


@dataclass
class Settings:
    steps: int              # FitRequest.steps of the recipe
    batch_size: int
    eval_batch_size: int
    num_denoise_steps: int | None
    eval_fraction: float
    eval_frames: int | None
    lora_rank: int
    checkpointing: str


def recipe_settings(recipe: Recipe, batch_size: int | None) -> Settings:
    fit = FitRequest(backbone=recipe.backbones[0].name, encoder=recipe.encoders[0].name, suite=recipe.suites[0],
                     **recipe.fit)
    if recipe.objective != "flow":
        raise SystemExit(f"{recipe.path}: bench_protocol measures flow recipes, not objective {recipe.objective!r}")
    return Settings(fit.steps, batch_size or fit.batch_size, fit.eval_batch_size, fit.num_denoise_steps,
                    fit.eval_fraction, fit.eval_frames, fit.lora_rank, fit.recompute)


def held_out_frames(suite: str, settings: Settings) -> int:
    """lerobot/libero's frames of `suite` times the held-out share, capped by the recipe's eval_frames."""
    if suite not in LIBERO_COUNTS:
        raise SystemExit(f"suite {suite!r}: lerobot/libero's counts know {', '.join(LIBERO_COUNTS)}")
    frames = round(LIBERO_COUNTS[suite][1] * settings.eval_fraction)
    return min(frames, settings.eval_frames) if settings.eval_frames else frames


def load(name: str, a: argparse.Namespace, device: torch.device, dtype_name: str):
    """The backbone (released geometry built into --hub when missing, or tiny) and its load seconds."""
    t0 = time.perf_counter()
    if a.tiny:
        adapter = load_backbone(name, "tiny", device=str(device), dataset_stats=unit_stats(),
                                tiny=TinyBuild(cameras=LIBERO.cameras))
        return adapter, time.perf_counter() - t0
    if name not in BUILDERS:
        raise SystemExit(f"no released-geometry builder for {name} (devtools.released knows "
                         f"{', '.join(BUILDERS)}): run it with --tiny")
    options = {"dtype": {"bf16": "bfloat16", "fp32": "float32"}[dtype_name]} if name == "pi05" else {}
    repo = f"graftcache-bench/{name}-libero-random" + (f"-{dtype_name}" if options else "")
    ref = a.hub / f"models--{repo.replace('/', '--')}" / "refs" / "main"
    if not (ref.is_file() and built_here(ref.parents[1] / "snapshots" / ref.read_text())):
        BUILDERS[name](repo, cache=a.hub, **options)
    t0 = time.perf_counter()
    return load_backbone(name, repo, device=str(device)), time.perf_counter() - t0


def kinds_of(recipe: Recipe, name: str, adapter, native_width: int) -> dict[tuple[str, str], Kind]:
    """(encoder, control) -> the kind of cell it is, for one backbone."""
    out = {}
    for entry in recipe.encoders:
        spec = get_spec(entry.name)
        for control_name in ("none", *recipe.controls):
            control = get_control(control_name)
            grid = control.grid or adapter.token_grid
            width = (adapter.lm_width if control.extra else native_width) if control.native_cache else spec.width
            out[entry.name, control_name] = Kind(name, grid[0] * grid[1], width, control.lora, control.train,
                                                 control.native_cache)
    return out


def synthetic_raw(adapter, features: torch.Tensor, rows: np.ndarray, g: torch.Generator, *,
                  actions: bool = True) -> dict:
    """A raw policy batch: every camera's synthetic features at `rows`, random state/actions, LIBERO's prompt."""
    b = len(rows)
    picks = torch.from_numpy(rows % len(features))
    raw = {feature_key(key): features[picks].float() for key in adapter.cameras}
    raw["observation.state"] = torch.randn(b, adapter.state_dim, generator=g) * 0.5
    raw["task"] = ["put the black bowl on the plate"] * b
    if actions:
        raw["action"] = torch.randn(b, adapter.chunk_size, adapter.action_dim, generator=g) * 0.5
        raw["action_is_pad"] = torch.zeros(b, adapter.chunk_size, dtype=torch.bool)
    return raw


def sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def measure_kind(adapter, kind: Kind, settings: Settings, a: argparse.Namespace, dtype: torch.dtype) -> dict:
    """Step seconds and FLOPs, scoring seconds and FLOPs per frame, and peak device memory of one cell kind."""
    device = adapter.device
    adapter.reset()
    torch.manual_seed(0)
    make = GraftProjector if kind.train else get_control("native").projector  # the one eval-only control
    adapter.graft(make(kind.width, adapter.lm_width))
    if kind.lora:
        adapter.add_lora(rank=settings.lora_rank)
    g = torch.Generator().manual_seed(0)
    features = torch.randn(POOL_FRAMES, kind.tokens, kind.width, generator=g).half()
    out: dict = {}
    b = settings.batch_size
    if kind.train:
        params = [p for p in adapter.policy.parameters() if p.requires_grad]
        opt = torch.optim.AdamW(params, lr=1e-3)

        def draw(gen: torch.Generator) -> dict:
            return synthetic_raw(adapter, features, torch.randint(0, 10**9, (b,), generator=gen).numpy(), gen)

        def steps(n: int) -> None:
            optimise(adapter, draw, steps=n, batch_size=b, optimizer=opt, generator=g, dtype=dtype, show=False)
            sync(device)

        def counted() -> int:
            """FLOPs of one step: the untimed warm-up (under auto, also the test whether a step fits)."""
            with FlopCounterMode(display=False) as flops:
                steps(1)
            return flops.get_total_flops()

        # auto: the backbone's recompute plans, least recompute first, until a step does not run out of memory
        plans = adapter.recompute_plans if settings.checkpointing == "auto" else (settings.checkpointing,)
        for plan in plans:
            adapter.set_recompute_plan(plan)
            if device.type == "cuda":
                torch.cuda.reset_peak_memory_stats(device)
            try:
                out["step_flops"] = counted()
                break
            except torch.OutOfMemoryError:
                if plan == plans[-1]:
                    raise
            # the next plan is tried after the except block, whose traceback holds the step's activations
            opt.zero_grad(set_to_none=True)
            gc.collect()
            torch.cuda.empty_cache()
        t0 = time.perf_counter()
        steps(a.steps)
        out["step_s"] = (time.perf_counter() - t0) / a.steps
        out["activation_checkpointing"] = adapter.recompute_plan
        out["peak_step_gb"] = torch.cuda.max_memory_allocated(device) / 1e9 if device.type == "cuda" else None
    adapter.set_recompute_plan("off")
    adapter.policy.eval()
    eb = min(settings.eval_batch_size, a.eval_frames)

    def score(n_frames: int) -> None:
        done = 0
        while done < n_frames:
            rows = np.arange(done, min(done + eb, n_frames))
            noise = frame_noise(rows, adapter.chunk_size, adapter.max_action_dim)
            with torch.no_grad(), autocast(device, dtype):
                batch = adapter.prepare(synthetic_raw(adapter, features, rows, g, actions=False))
                adapter.predict(batch, noise=noise, num_steps=settings.num_denoise_steps)
            done += len(rows)
        sync(device)

    with FlopCounterMode(display=False) as flops:  # the untimed warm-up
        score(eb)
    out["eval_flops_per_frame"] = flops.get_total_flops() / eb
    t0 = time.perf_counter()
    score(a.eval_frames)
    out["eval_s_per_frame"] = (time.perf_counter() - t0) / a.eval_frames
    return out


def decode_seconds_per_frame(dataset: Path) -> float:
    """The project's decoder on one episode (every camera), per frame: sequential throughput."""
    from graftcache.datasets import open_dataset  # PyAV: imported only here (benchmarks/gpu_check.py runs without it)

    source = open_dataset(dataset)
    episode = source.meta.episodes[0]
    source.decode_episode(episode.index, list(source.meta.cameras))  # warm-up (file open, codec init)
    t0 = time.perf_counter()
    source.decode_episode(episode.index, list(source.meta.cameras))
    return (time.perf_counter() - t0) / (episode.length * len(source.meta.cameras))


def encode_seconds_per_image(forward: Callable[[torch.Tensor], object], size: int, batch: int,
                             device: torch.device, dtype: torch.dtype) -> float:
    frames = torch.rand(batch, 3, size, size, device=device)
    with torch.no_grad(), autocast(device, dtype):
        forward(frames)
        sync(device)
        t0 = time.perf_counter()
        forward(frames)
        sync(device)
    return (time.perf_counter() - t0) / batch


def peak_flops(device: torch.device, dtype: torch.dtype, given: float | None) -> tuple[float, str]:
    """FLOP/s the bound is taken against, and where the figure comes from."""
    if given:
        return given * 1e12, f"--peak-tflops {given}"
    if device.type == "cuda":
        name = torch.cuda.get_device_name(device)
        for key, tflops in GPU_PEAKS.items():
            if key in name:
                return tflops * 1e12, f"{name}: {tflops:g} TFLOP/s dense bf16 (data sheet)"
        raise SystemExit(f"no bf16 peak known for {name}: pass --peak-tflops")
    n = 2048
    x = torch.randn(n, n, dtype=dtype)
    x @ x
    t0 = time.perf_counter()
    for _ in range(3):
        x @ x
    measured = 3 * 2 * n ** 3 / (time.perf_counter() - t0)
    return measured, f"measured: {n}^3 matmul in {dtype} on {torch.get_num_threads()} threads"


def cells(recipe: Recipe) -> Iterator[tuple[str, str, str, str]]:
    """(backbone, suite, encoder, control) of every row the sweep computes (seeds counted by the caller); a
    native-cache control's row does not depend on the encoder, so it comes once, under the first encoder."""
    for backbone in recipe.backbones:
        for suite in recipe.suites:
            for i, entry in enumerate(recipe.encoders):
                for control in ("none", *recipe.controls):
                    if i == 0 or not get_control(control).native_cache:
                        yield backbone.name, suite, entry.name, control


def project(recipe: Recipe, settings: Settings, measured: dict, loads: dict[str, float], decode_s: float,
            encode_s: dict[str, float], tower_s: dict[str, float], cameras: dict[str, int],
            peak: float) -> dict:
    """Hours of the recipe's protocol, cached and online, and its FLOP bound, from the per-kind measurements."""
    seeds = len(recipe.seeds)
    training = evaluation = online = flops = 0.0
    for backbone, suite, encoder, control in cells(recipe):
        m = measured[backbone][encoder, control]
        frames = held_out_frames(suite, settings)
        frame_in = cameras[backbone] * (decode_s + (tower_s[backbone] if m["native_tower"] else encode_s[encoder]))
        train_s = settings.steps * m.get("step_s", 0.0)
        eval_s = frames * m["eval_s_per_frame"]
        training += seeds * train_s
        evaluation += seeds * eval_s
        steps_online = settings.steps * settings.batch_size * frame_in if m["train"] else 0.0
        online += seeds * (train_s + eval_s + steps_online + frames * frame_in)
        flops += seeds * (settings.steps * m.get("step_flops", 0) + frames * m["eval_flops_per_frame"])
    load_s = sum(loads.values())
    suite_frames = sum(LIBERO_COUNTS[s][1] for s in recipe.suites)
    extraction = sum(suite_frames * len(LIBERO.cameras) * (decode_s + encode_s[e.name]) for e in recipe.encoders)
    hours = {"loads_h": load_s / 3600, "training_h": training / 3600, "evaluation_h": evaluation / 3600}
    hours["projected_h"] = hours["loads_h"] + hours["training_h"] + hours["evaluation_h"]
    hours["online_h"] = (load_s + online) / 3600
    hours["extraction_h"] = extraction / 3600
    hours["flops"] = flops
    hours["flop_bound_h_100"] = flops / peak / 3600
    hours["flop_bound_h_40"] = flops / (0.4 * peak) / 3600
    return hours


def only(recipe: Recipe, axis: str, names: str | None, p: argparse.ArgumentParser) -> Recipe:
    """The recipe with only the named entries of `axis` (backbones or encoders); all of them when None."""
    if names is None:
        return recipe
    wanted = names.split(",")
    entries = tuple(e for e in getattr(recipe, axis) if e.name in wanted)
    missing = sorted(set(wanted) - {e.name for e in entries})
    if missing:
        p.error(f"--{axis} {', '.join(missing)}: not in {recipe.path}")
    return replace(recipe, **{axis: entries})


def slug(text: str) -> str:
    return re.sub(r"[^a-z0-9]+", "-", text.lower()).strip("-")


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--recipe", type=Path, default=ROOT / "cli" / "paper.toml")
    p.add_argument("--device", default=None, help="cpu, cuda or cuda:N (default: the recipe's)")
    p.add_argument("--compute-dtype", default="auto", choices=("auto", "bf16", "fp32"))
    p.add_argument("--steps", type=int, default=24, help="timed flow steps per cell kind (after one warm-up)")
    p.add_argument("--eval-frames", type=int, default=128, help="timed held-out frames per cell kind")
    p.add_argument("--batch-size", type=int, default=None, help="training batch (default: the recipe's)")
    p.add_argument("--tiny", action="store_true", help="the tiny backbones (a CPU smoke test), not released size")
    p.add_argument("--backbones", default=None, help="comma list: only these of the recipe's backbones")
    p.add_argument("--encoders", default=None, help="comma list: only these of the recipe's encoders")
    p.add_argument("--dataset", type=Path, default=DEFAULT_DATASET, help="decoded for the online protocol's rate")
    p.add_argument("--hub", type=Path, default=DEFAULT_HUB, help="HF hub cache for the released-geometry builds")
    p.add_argument("--peak-tflops", type=float, default=None, help="the device's peak (default: see the docstring)")
    p.add_argument("--threads", type=int, default=None, help="torch intra-op threads (default: all cores)")
    p.add_argument("--out", type=Path, default=None, help="JSON file (default: benchmarks/results/<name>.json)")
    a = p.parse_args(argv)
    if a.steps < 1 or a.eval_frames < 1:
        p.error("--steps and --eval-frames must be at least 1")

    recipe = only(only(load_recipe(a.recipe), "backbones", a.backbones, p), "encoders", a.encoders, p)
    settings = recipe_settings(recipe, a.batch_size)
    device = resolve_device(a.device or recipe.device)
    dtype_name = resolve_compute_dtype(a.compute_dtype, device)
    dtype = resolve_dtype(dtype_name)
    set_main_threads(a.threads)
    gpu = torch.cuda.get_device_name(device) if device.type == "cuda" else None
    where = machine()
    print(f"machine: {where}" + (f"; {gpu}" if gpu else "") + f"; device {device}, compute {dtype_name}", flush=True)

    decode_s = decode_seconds_per_frame(a.dataset)
    print(f"decode: {decode_s * 1e3:.1f} ms a frame (a camera)", flush=True)
    encode_s = {}
    for entry in recipe.encoders:
        encoder = load_encoder(entry.name, random_init=True, device=device)
        size = encoder.spec.image_size
        encode_s[entry.name] = encode_seconds_per_image(encoder.forward_grid, size, settings.batch_size, device, dtype)
        print(f"encoder {entry.name}: {encode_s[entry.name] * 1e3:.1f} ms an image", flush=True)
        del encoder
    measured: dict[str, dict] = {}
    kinds_json, loads, tower_s, cameras = [], {}, {}, {}
    with hub_cache(a.hub) if not a.tiny else contextlib.nullcontext():
        for entry in recipe.backbones:
            adapter, loads[entry.name] = load(entry.name, a, device, dtype_name)
            print(f"{entry.name}: loaded in {loads[entry.name]:.1f} s", flush=True)
            cameras[entry.name] = len(adapter.cameras)
            side = LIBERO.image_size
            tower_s[entry.name] = encode_seconds_per_image(adapter.native_tokens, side, settings.batch_size, device,
                                                           dtype)
            native_width = adapter.native_patch_grid(torch.zeros(1, 3, side, side)).shape[-1]
            by_kind: dict[Kind, dict] = {}
            measured[entry.name] = {}
            for cell, kind in kinds_of(recipe, entry.name, adapter, native_width).items():
                if kind not in by_kind:
                    by_kind[kind] = {**asdict(kind), **measure_kind(adapter, kind, settings, a, dtype)}
                    kinds_json.append(by_kind[kind])
                    print(json.dumps(by_kind[kind]), flush=True)
                measured[entry.name][cell] = by_kind[kind]
            del adapter
            gc.collect()  # the graft's instance override makes policy and adapter a cycle
            if device.type == "cuda":
                torch.cuda.empty_cache()

    peak, peak_source = peak_flops(device, dtype, a.peak_tflops)
    hours = project(recipe, settings, measured, loads, decode_s, encode_s, tower_s, cameras, peak)
    n_rows = sum(1 for _ in cells(recipe)) * len(recipe.seeds)
    report = {
        "recipe": str(a.recipe), "device": gpu or str(device), "cpu": where, "compute_dtype": dtype_name,
        "tiny": a.tiny, "bench_steps": a.steps, "bench_eval_frames": a.eval_frames, "settings": asdict(settings),
        "rows": n_rows, "held_out_frames": {s: held_out_frames(s, settings) for s in recipe.suites},
        "loads_s": loads, "decode_s_per_frame": decode_s, "encode_s_per_image": encode_s,
        "native_tower_s_per_image": tower_s, "kinds": kinds_json,
        "peak_flops": peak, "peak_source": peak_source, **hours,
    }
    out = a.out or ROOT / "benchmarks" / "results" / (
        f"bench_protocol_{recipe.name}{'_tiny' if a.tiny else ''}_{slug(gpu or device.type)}_{dtype_name}.json")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(report, indent=1))
    print(f"{recipe.name}: {n_rows} rows; projected {hours['projected_h']:.2f} device-hours (loads "
          f"{hours['loads_h']:.3f} + training {hours['training_h']:.2f} + evaluation {hours['evaluation_h']:.2f}); "
          f"online {hours['online_h']:.2f} h; stage 1 {hours['extraction_h']:.2f} h; FLOP bound "
          f"{hours['flop_bound_h_100']:.2f} h at 100%, {hours['flop_bound_h_40']:.2f} h at 40% of {peak / 1e12:.3g} "
          f"TFLOP/s ({peak_source}) -> {out}")
    return report


if __name__ == "__main__":
    main()
