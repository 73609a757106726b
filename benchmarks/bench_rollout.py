#!/usr/bin/env python
"""Episodes per hour of `graftcache rollout` at 1 and 2 workers (`--workers`) on the same episodes, and what an
episode's step is made of (the env's step, rendering included, vs the policy's call).

    python benchmarks/bench_rollout.py [--results R --cache C] [--episodes-per-task 2] [--max-steps 20]
                                       [--repeats 2] [--workers 1,2]

Each measured run is the whole command a user runs (`python -m graftcache rollout ... --workers N`, a fresh process,
into a fresh rollouts file), so its wall time holds the imports, each worker's simulator build and reset: the figure
a user waits for, which startup dominates at small settings (the ratio grows with episodes and steps). Exports are made
once beforehand and copied beside each rollouts file, so no run pays for them. Without --results, two cells (a plain
graft of a random-init ViT-tiny and its zero-image control on a 1-step tiny SmolVLA) are fitted first, as the CI smoke
fits them. Prints the machine (CPU model, whether it has avx512_bf16, cores, load), the median episodes/hour per worker
count, their ratio, and the per-step costs of one in-process episode.
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "data" / "libero_sample"
ENCODER = "timm:vit_tiny_patch16_224"


def cpu() -> str:
    """lscpu's model name and whether the CPU computes bf16 in hardware (avx512_bf16), cores and load now."""
    lscpu = subprocess.run(["lscpu"], capture_output=True, text=True).stdout
    model = next((ln.split(":", 1)[1].strip() for ln in lscpu.splitlines() if ln.startswith("Model name")), "?")
    bf16 = "avx512_bf16" in Path("/proc/cpuinfo").read_text()
    return (f"{model}, avx512_bf16 {'present' if bf16 else 'absent'}, {os.cpu_count()} cores; "
            f"uptime: {subprocess.run(['uptime'], capture_output=True, text=True).stdout.strip()}")


def graftcache(*argv: object, check: bool = True) -> subprocess.CompletedProcess:
    env = {**os.environ, "HF_HUB_OFFLINE": "1"}
    done = subprocess.run([sys.executable, "-m", "graftcache", *map(str, argv)], env=env, capture_output=True,
                          text=True)
    if check and done.returncode:
        sys.exit(f"graftcache {argv[0]} failed:\n{done.stderr[-3000:]}")
    return done


def fit_cells(folder: Path) -> tuple[Path, Path]:
    """Two fitted cells of the sample's libero_object task 0 (the CI smoke's), into `folder`."""
    cache, policy, results = folder / "cache", folder / "policy", folder / "results.parquet"
    graftcache("train-tiny", "--backbone", "smolvla", "--dataset", SAMPLE, "--steps", 1, "--out", policy,
               "--cache", cache)
    graftcache("extract", "--encoder", ENCODER, "--random-init", "--dataset", SAMPLE, "--episodes", "18-21",
               "--frame-stride", 8, "--num-workers", 0, "--batch-size", 16, "--no-progress", "--cache", cache)
    graftcache("fit", "--backbone", "smolvla", "--policy", policy, "--encoder", ENCODER, "--dataset", SAMPLE,
               "--suite", "libero_object", "--seeds", 1, "--controls", "zero-image", "--steps", 2, "--batch-size", 4,
               "--eval-fraction", 0.5, "--eval-frames", 4, "--num-denoise-steps", 2, "--cache", cache, "--results",
               results, "--no-progress")
    return results, cache


def step_costs(results: Path, cache: Path, exports: Path, run_id: str, max_steps: int) -> dict[str, float]:
    """Mean seconds a step of the env's step (physics and both cameras' rendering) and of the policy's call
    (select_action, the model's call amortised over its action chunk; the processors excluded), and the whole
    episode, of one in-process episode after a warm-up one, at the rollout's policy threads
    (graftcache.rollout.libero.POLICY_THREADS)."""
    import gymnasium as gym
    import polars as pl

    from graftcache.export.modeling_graftcache import GraftcachePolicy
    from graftcache.rollout.episodes import Episode
    from graftcache.rollout.libero import LiberoSimulator

    timings: dict[str, list[float]] = {"env step": [], "policy call": []}

    def timed(name: str, fn):  # noqa: ANN001, ANN202
        def wrapper(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
            t0 = time.perf_counter()
            out = fn(*args, **kwargs)
            timings[name].append(time.perf_counter() - t0)
            return out
        return wrapper

    gym.vector.SyncVectorEnv.step = timed("env step", gym.vector.SyncVectorEnv.step)
    GraftcachePolicy.select_action = timed("policy call", GraftcachePolicy.select_action)
    row = pl.read_parquet(results).filter(pl.col("run_id") == run_id).row(0, named=True)
    sim = LiberoSimulator(results, exports, cache=str(cache), runs=None, max_steps=max_steps, log=lambda _: None)
    try:
        for k, _ in enumerate(("warm-up", "measured")):
            for v in timings.values():
                v.clear()
            (outcome,) = sim.run(row, [Episode(run_id, "libero_object", 0, k, 1000 + k, max_steps)])
    finally:
        sim.close()
    costs = {name: statistics.fmean(v) for name, v in timings.items()}
    costs["episode"] = outcome.seconds
    costs["steps"] = outcome.steps
    return costs


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--results", type=Path, default=None, help="results file of cells to roll out (default: fit two)")
    ap.add_argument("--cache", type=Path, default=None, help="the cache root its fits read")
    ap.add_argument("--episodes-per-task", type=int, default=2)
    ap.add_argument("--max-steps", type=int, default=20)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--workers", default="1,2")
    args = ap.parse_args()
    counts = [int(w) for w in args.workers.split(",")]
    print(f"machine: {cpu()}", flush=True)
    with tempfile.TemporaryDirectory(prefix="bench_rollout_") as tmp:
        tmp_path = Path(tmp)
        results, cache = (args.results, args.cache) if args.results else fit_cells(tmp_path)
        import polars as pl

        cells = pl.read_parquet(results).filter(pl.col("suite") == "libero_object")["run_id"].to_list()
        exports = tmp_path / "exports"
        for run_id in cells:
            graftcache("export", run_id, "--results", results, "--out", exports / run_id, "--cache", cache)
        episodes = len(cells) * args.episodes_per_task
        print(f"{len(cells)} cell(s) x libero_object task 0 x {args.episodes_per_task} episode(s) = {episodes} "
              f"episodes of {args.max_steps} steps, {args.repeats} repeat(s)", flush=True)
        rates: dict[int, list[float]] = {n: [] for n in counts}
        inside: dict[int, list[float]] = {n: [] for n in counts}
        for repeat in range(args.repeats):
            for n in counts:
                folder = tmp_path / f"run{repeat}-w{n}"
                shutil.copytree(exports, folder / "exports")
                t0 = time.perf_counter()
                graftcache("rollout", results, "--run-ids", ",".join(cells), "--suites", "libero_object", "--tasks",
                           0, "--episodes-per-task", args.episodes_per_task, "--max-steps", args.max_steps,
                           "--cache", cache, "--rollouts", folder / "rollouts.parquet", "--workers", n)
                wall = time.perf_counter() - t0
                rows = pl.read_parquet(folder / "rollouts.parquet")
                assert rows.height == episodes, rows.height
                rates[n].append(episodes / wall * 3600)
                inside[n].append(statistics.median(rows["seconds"].to_list()))
                print(f"  repeat {repeat}, {n} worker(s): {wall:.0f} s wall, {rates[n][-1]:.0f} episodes/hour, "
                      f"median episode {inside[n][-1]:.1f} s inside its worker; load {os.getloadavg()[0]:.2f}",
                      flush=True)
        costs = step_costs(results, cache, exports, cells[0], args.max_steps)
    medians = {n: statistics.median(r) for n, r in rates.items()}
    for n in counts:
        print(f"{n} worker(s): median {medians[n]:.0f} episodes/hour (wall, startup included); median episode "
              f"{statistics.median(inside[n]):.1f} s inside its worker")
    # past the startup (imports, simulator builds), N workers finish N episodes per episode time as measured inside
    steady = {n: n * 3600 / statistics.median(inside[n]) for n in counts}
    if len(counts) > 1:
        print(f"ratio {counts[-1]} vs {counts[0]} worker(s): {medians[counts[-1]] / medians[counts[0]]:.2f} (wall); "
              f"past the startup {steady[counts[0]]:.0f} vs {steady[counts[-1]]:.0f} episodes/hour, "
              f"{steady[counts[-1]] / steady[counts[0]]:.2f}")
    print(f"one in-process episode ({costs['steps']:.0f} steps, {costs['episode']:.1f} s with its reset): env step "
          f"{costs['env step'] * 1000:.0f} ms, policy call {costs['policy call'] * 1000:.0f} ms (means a step)")
    print(f"machine after: {cpu()}")


if __name__ == "__main__":
    main()
