#!/usr/bin/env python
"""Seconds per cell against `--cells-per-pass`: what sharing one pass of the frozen backbone buys.

    python benchmarks/bench_fuse.py [--dataset DIR] [--backbones smolvla,pi05] [--cells 1,2,4] [--steps 30]
                                    [--threads 1] [--json benchmarks/results/bench_fuse_cpu_run2.json]

For each backbone (tiny, random init: a step's cost does not depend on what the weights learned) it caches one
encoder, then fits the same 4 cells (4 seeds of the plain graft: one pass key) with each `--cells-per-pass` N,
through the real Fitter (streamed features, training, held-out scoring, rows), and prints wall seconds per cell and
the ratio to N=1 (median of `--rounds` fits per N, interleaved across N). The backbone is loaded and each cache's
numerics checked once, before the timed runs (`--num-workers 0`: features read in this process, so the timings count
no reader processes' start-up). The grafted step alone (features in memory, no scoring) is timed too, as seconds per
cell-step: the part a pass shares; `--released smolvla` times that step at the released geometry as well. The JSON
(with `--json`) names the machine; the backbones' specs (cells_per_pass) cite it. """

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from common import DEFAULT_DATASET, machine, median_seconds, warm_page_cache

from graftcache.backbones import load_backbone
from graftcache.backbones.loaded import LoadedBackbones
from graftcache.extract import ExtractRequest, extract
from graftcache.fit.data import load_lowdim
from graftcache.fit.local import Fitter
from graftcache.fit.loop import Learner, optimise_together, raw_batch
from graftcache.fit.run import FitRequest
from graftcache.fit.stream import FeatureSource
from graftcache.graft import FusedProjector, GraftProjector, feature_key
from graftcache.pretrain import dataset_stats
from graftcache.runtime import resolve_compute_dtype, resolve_device, resolve_dtype, set_main_threads
from graftcache.store import FeatureCache

SUITE = "libero_spatial"
CELLS = 4  # cells fitted per setting: every N in --cells divides it


def _quiet(_: str) -> None:
    pass


def synced_step(adapter, learners: list[Learner], batch_size: int, dtype: torch.dtype, route) -> None:
    """One fused step, finished: on CUDA the host waits for the device, so a timing counts the step, not its launch."""
    optimise_together(adapter, learners, steps=1, batch_size=batch_size, dtype=dtype, route=route, show=False)
    if adapter.device.type == "cuda":
        torch.cuda.synchronize(adapter.device)


def step_seconds(adapter, low, feats, cams, n: int, batch_size: int, dtype: torch.dtype, repeats: int) -> float:
    """Median seconds of one grafted step of `n` cells (batch n x batch_size), features in memory."""
    width = next(iter(feats.values())).shape[-1]
    projectors = [GraftProjector(width, adapter.lm_width) for _ in range(n)]
    fused = FusedProjector(projectors)
    adapter.reset()
    adapter.graft(fused)

    def draw(generator: torch.Generator) -> dict:
        pos = torch.randint(0, len(low), (batch_size,), generator=generator).numpy()
        return raw_batch(low, pos, {c: f[torch.from_numpy(pos)] for c, f in feats.items()}, cams)

    learners = [Learner(draw, torch.optim.AdamW(list(p.parameters()), lr=1e-3), torch.Generator().manual_seed(i))
                for i, p in enumerate(projectors)]
    seconds = median_seconds(lambda: synced_step(adapter, learners, batch_size, dtype, fused.rows), repeats)
    adapter.reset()
    return seconds


def released_step_seconds(name: str, root: Path, counts: list[int], batch_size: int, dtype: torch.dtype,
                          repeats: int, rounds: int, device: torch.device) -> dict[int, float]:
    """Seconds a cell-step at the released geometry (random init, devtools.released), synthetic
    features of the backbone's token grid at SigLIP-B's width (768) and LIBERO's state and action sizes."""
    from devtools.released import LIBERO, build_pi05, build_smolvla, hub_cache

    builders = {"smolvla": build_smolvla, "pi05": build_pi05}
    with hub_cache(root / "hub"):
        folder = builders[name](f"bench/{name}-released", cache=root / "hub")
        adapter = load_backbone(name, folder, device=str(device))
        tokens = adapter.token_grid[0] * adapter.token_grid[1]
        generator = torch.Generator().manual_seed(0)
        n_frames = 64
        feats = {c: torch.randn(n_frames, tokens, 768, generator=generator) for c in adapter.cameras}
        state = torch.randn(n_frames, LIBERO.state_dim, generator=generator)
        actions = torch.randn(n_frames, adapter.chunk_size, LIBERO.action_dim, generator=generator)

        def step(n: int) -> float:
            projectors = [GraftProjector(768, adapter.lm_width) for _ in range(n)]
            fused = FusedProjector(projectors)
            adapter.reset()
            adapter.graft(fused)

            def draw(g: torch.Generator) -> dict:
                pos = torch.randint(0, n_frames, (batch_size,), generator=g)
                raw = {feature_key(c): f[pos] for c, f in feats.items()}
                return {**raw, "observation.state": state[pos], "task": ["put the bowl on the plate"] * batch_size,
                        "action": actions[pos], "action_is_pad": torch.zeros(batch_size, adapter.chunk_size,
                                                                             dtype=torch.bool)}

            learners = [Learner(draw, torch.optim.AdamW(list(p.parameters()), lr=1e-3),
                                torch.Generator().manual_seed(i)) for i, p in enumerate(projectors)]
            return median_seconds(lambda: synced_step(adapter, learners, batch_size, dtype, fused.rows), repeats) / n

        times: dict[int, list[float]] = {n: [] for n in counts}
        for _ in range(rounds):
            for n in counts:
                times[n].append(step(n))
        adapter.reset()
    return {n: float(np.median(t)) for n, t in times.items()}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--dataset", type=Path, default=DEFAULT_DATASET)
    p.add_argument("--encoder", default="timm:vit_tiny_patch16_224")
    p.add_argument("--episodes", default="0-11", help="episodes to cache (libero_spatial ones in the sample)")
    p.add_argument("--backbones", default="smolvla,pi05")
    p.add_argument("--cells", default="1,2,4", help="--cells-per-pass values to time")
    p.add_argument("--steps", type=int, default=30)
    p.add_argument("--batch-size", type=int, default=16)
    p.add_argument("--eval-frames", type=int, default=64)
    p.add_argument("--num-denoise-steps", type=int, default=4)
    p.add_argument("--compute-dtype", default="auto")
    p.add_argument("--repeats", type=int, default=10, help="timed steps per N (step timing)")
    p.add_argument("--rounds", type=int, default=3, help="timed fits per N, interleaved across N (median)")
    p.add_argument("--threads", type=int, help="torch threads (default: graftcache's, one per core); on a machine "
                   "shared past its cores, 1 keeps OpenMP's barriers from waiting on descheduled threads")
    p.add_argument("--released", default="", help="comma list of backbones to time at the released geometry too "
                   "(step only, random init; smolvla: ~450M parameters, pi05: ~4B, far past a CPU's budget)")
    p.add_argument("--released-batch-size", type=int, default=2)
    p.add_argument("--device", default="cpu", help="cpu, cuda or cuda:N (the fits and the steps run there)")
    p.add_argument("--json", type=Path, help="write the measurements here")
    a = p.parse_args()

    if a.threads:
        os.environ["OMP_NUM_THREADS"] = str(a.threads)  # what every fit's set_main_threads grants itself
    set_main_threads()
    counts = [int(c) for c in a.cells.split(",")]
    if any(CELLS % n for n in counts):
        raise SystemExit(f"--cells: each must divide {CELLS}")
    lo, hi = (int(v) for v in a.episodes.split("-"))
    warm_page_cache(a.dataset)
    where = machine()
    device = resolve_device(a.device)
    compute = resolve_compute_dtype(a.compute_dtype, device)
    print(f"machine: {where}; compute dtype {compute}")
    report: dict = {"machine": where, "threads": torch.get_num_threads(), "device": str(device),
                    "compute_dtype": compute,
                    "steps": a.steps, "batch_size": a.batch_size, "eval_frames": a.eval_frames,
                    "num_denoise_steps": a.num_denoise_steps,
                    "cells": CELLS, "backbones": {}}
    with tempfile.TemporaryDirectory(prefix="bench_fuse_") as tmp:
        root = Path(tmp)
        key = extract(ExtractRequest(dataset=str(a.dataset), encoder=a.encoder, random_init=True,
                                     episodes=tuple(range(lo, hi + 1)), num_workers=1, cache=str(root / "cache"),
                                     progress=False), log=_quiet).key
        cache = FeatureCache(root / "cache" / key)
        for name in filter(None, a.backbones.split(",")):
            folder = root / f"policy_{name}"
            load_backbone(name, "tiny", dataset_stats=dataset_stats(cache.index())).save(folder)
            loaded, numerics = LoadedBackbones(_quiet), {}

            def request(n: int, out: str, seeds: tuple[int, ...] = tuple(range(CELLS)), name: str = name,
                        folder: Path = folder) -> FitRequest:
                return FitRequest(backbone=name, encoder=a.encoder, suite=SUITE, policy=str(folder), cache_key=key,
                                  seeds=seeds, steps=a.steps, batch_size=a.batch_size, eval_frames=a.eval_frames,
                                  num_denoise_steps=a.num_denoise_steps, num_workers=0, compute_dtype=compute,
                                  cells_per_pass=n, cache=str(root / "cache"), results=str(root / out),
                                  device=str(device),
                                  progress=False, command="bench_fuse")

            Fitter(request(1, "warm.parquet", seeds=(99,)), log=_quiet, backbones=loaded, numerics=numerics).run()
            times: dict[int, list[float]] = {n: [] for n in counts}
            for rep in range(a.rounds):  # interleaved, so a change in the machine's load reaches every N alike
                for n in counts:
                    t0 = time.perf_counter()
                    rows = Fitter(request(n, f"{name}-{n}-{rep}.parquet"), log=_quiet, backbones=loaded,
                                  numerics=numerics).run()
                    times[n].append((time.perf_counter() - t0) / len(rows))
                    assert {r["cells_per_pass"] for r in rows} == {n}
            per_cell = {n: float(np.median(t)) for n, t in times.items()}
            adapter = loaded.get(name, folder, str(device))
            cams = {c: c for c in adapter.cameras}
            low = load_lowdim(cache, SUITE, chunk=adapter.chunk_size)
            grid = adapter.token_grid
            feats = FeatureSource.of(cache, list(cams.values()), grid).read(low.rows)
            step_times: dict[int, list[float]] = {n: [] for n in counts}
            for _ in range(a.rounds):
                for n in counts:
                    step_times[n].append(step_seconds(adapter, low, feats, cams, n, a.batch_size,
                                                      resolve_dtype(compute), a.repeats) / n)
            steps = {n: float(np.median(t)) for n, t in step_times.items()}
            for n in counts:
                print(f"{name}: {n} cell(s) per pass: {per_cell[n]:.2f} s a cell "
                      f"({per_cell[n] / per_cell[1]:.2f}x N=1), "
                      f"step {steps[n] * 1e3:.1f} ms a cell-step ({steps[n] / steps[1]:.2f}x)")
            report["backbones"][name] = {"seconds_per_cell": per_cell, "seconds_per_cell_rounds": times,
                                         "seconds_per_cell_step": steps,
                                         "grid": list(grid), "lm_width": adapter.lm_width,
                                         "fastest": min(counts, key=lambda n: per_cell[n])}
        for name in filter(None, a.released.split(",")):
            steps = released_step_seconds(name, root, counts, a.released_batch_size, resolve_dtype(compute),
                                          a.repeats, a.rounds, device)
            for n in counts:
                print(f"{name} at the released geometry: {n} cell(s) per pass: step {steps[n]:.2f} s a cell-step "
                      f"({steps[n] / steps[1]:.2f}x N=1; batch {a.released_batch_size} a cell)")
            report["released"] = {**report.get("released", {}), name: {"seconds_per_cell_step": steps,
                                                                       "batch_size": a.released_batch_size}}
    report["load_average_after"] = os.getloadavg()[0]
    if a.json:
        a.json.parent.mkdir(parents=True, exist_ok=True)
        a.json.write_text(json.dumps(report, indent=2, default=lambda v: float(np.asarray(v))) + "\n")
        print(f"wrote {a.json}")


if __name__ == "__main__":
    main()
