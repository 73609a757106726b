#!/usr/bin/env python
"""Episodes per hour of `graftcache rollout` at 1 and 2 workers (`--workers`) and with each reset (`--reset`:
soft, hard) on the same episodes, and what an episode is made of (the env's reset, its step, rendering included, vs
the policy's call).

    python benchmarks/bench_rollout.py [--results R --cache C] [--episodes-per-task 2] [--max-steps 20]
                                       [--repeats 2] [--workers 1,2] [--resets soft,hard]

Each measured run is the whole command a user runs (`python -m graftcache rollout ... --workers N`, a fresh process,
into a fresh rollouts file), so its wall time holds the imports, each worker's simulator build and reset: the figure
a user waits for, which startup dominates at small settings (the ratio grows with episodes and steps). Exports are made
once beforehand and copied beside each rollouts file, so no run pays for them. Without --results, two cells (a plain
graft of a random-init ViT-tiny and its zero-image control on a 1-step tiny SmolVLA) are fitted first, as the CI smoke
fits them. The arms (worker count x reset) run interleaved, each repeat in the reverse order of the one before, so
that a machine shared with other work weighs on each arm alike. Prints the machine (CPU model, whether it has
avx512_bf16, cores, load), the median episodes/hour per arm, their ratios, and the per-step and reset costs of an
in-process episode with each reset.
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

from closed_loop_cells import export_cells, fit_cells


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


def step_costs(results: Path, cache: Path, exports: Path, run_id: str, max_steps: int,
               resets: list[str]) -> dict[str, dict[str, float]]:
    """Per reset: mean seconds of the env's reset, of a step of the env's step (physics and both cameras' rendering)
    and of the policy's call (select_action, the model's call amortised over its action chunk; the processors
    excluded), and the whole episode, of one in-process episode after a warm-up one, at the rollout's policy threads
    (graftcache.rollout.simulator_setup.POLICY_THREADS)."""
    import gymnasium as gym
    import polars as pl

    from graftcache.export.modeling_graftcache import GraftcachePolicy
    from graftcache.rollout.episodes import Episode
    from graftcache.rollout.libero import LiberoSimulator

    timings: dict[str, list[float]] = {"env reset": [], "env step": [], "policy call": []}

    def timed(name: str, fn):  # noqa: ANN001, ANN202
        def wrapper(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
            t0 = time.perf_counter()
            out = fn(*args, **kwargs)
            timings[name].append(time.perf_counter() - t0)
            return out
        return wrapper

    gym.vector.SyncVectorEnv.reset = timed("env reset", gym.vector.SyncVectorEnv.reset)
    gym.vector.SyncVectorEnv.step = timed("env step", gym.vector.SyncVectorEnv.step)
    GraftcachePolicy.select_action = timed("policy call", GraftcachePolicy.select_action)
    row = pl.read_parquet(results).filter(pl.col("run_id") == run_id).row(0, named=True)
    sim = LiberoSimulator(results, exports, cache=str(cache), runs=None, max_steps=max_steps, log=lambda _: None)
    costs = {}
    try:
        for reset in resets:
            for k, _ in enumerate(("warm-up", "measured")):
                for v in timings.values():
                    v.clear()
                (outcome,) = sim.run(row, [Episode(run_id, "libero_object", 0, k, 1000 + k, max_steps, reset=reset)])
            costs[reset] = {name: statistics.fmean(v) for name, v in timings.items()}
            costs[reset]["episode"] = outcome.seconds
            costs[reset]["steps"] = outcome.steps
    finally:
        sim.close()
    return costs


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--results", type=Path, default=None, help="results file of cells to roll out (default: fit two)")
    ap.add_argument("--cache", type=Path, default=None, help="the cache root its fits read")
    ap.add_argument("--episodes-per-task", type=int, default=2)
    ap.add_argument("--max-steps", type=int, default=20)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--workers", default="1,2")
    ap.add_argument("--resets", default="soft", help="resets to compare, e.g. soft,hard (graftcache rollout --reset)")
    args = ap.parse_args()
    counts = [int(w) for w in args.workers.split(",")]
    resets = args.resets.split(",")
    arms = [(n, reset) for n in counts for reset in resets]
    print(f"machine: {cpu()}", flush=True)
    with tempfile.TemporaryDirectory(prefix="bench_rollout_") as tmp:
        tmp_path = Path(tmp)
        results, cache = (args.results, args.cache) if args.results else fit_cells(tmp_path)
        import polars as pl

        exports = tmp_path / "exports"
        cells = export_cells(results, cache, exports)
        episodes = len(cells) * args.episodes_per_task
        print(f"{len(cells)} cell(s) x libero_object task 0 x {args.episodes_per_task} episode(s) = {episodes} "
              f"episodes of {args.max_steps} steps, {args.repeats} repeat(s)", flush=True)
        rates: dict[tuple[int, str], list[float]] = {arm: [] for arm in arms}
        inside: dict[tuple[int, str], list[float]] = {arm: [] for arm in arms}
        for repeat in range(args.repeats):
            for n, reset in arms if repeat % 2 == 0 else arms[::-1]:
                folder = tmp_path / f"run{repeat}-w{n}-{reset}"
                shutil.copytree(exports, folder / "exports")
                t0 = time.perf_counter()
                graftcache("rollout", results, "--run-ids", ",".join(cells), "--suites", "libero_object", "--tasks",
                           0, "--episodes-per-task", args.episodes_per_task, "--max-steps", args.max_steps,
                           "--cache", cache, "--rollouts", folder / "rollouts.parquet", "--workers", n,
                           "--reset", reset)
                wall = time.perf_counter() - t0
                rows = pl.read_parquet(folder / "rollouts.parquet")
                assert rows.height == episodes, rows.height
                rates[n, reset].append(episodes / wall * 3600)
                inside[n, reset].append(statistics.median(rows["seconds"].to_list()))
                print(f"  repeat {repeat}, {n} worker(s), {reset} reset: {wall:.0f} s wall, "
                      f"{rates[n, reset][-1]:.0f} episodes/hour, median episode {inside[n, reset][-1]:.1f} s inside "
                      f"its worker; load {os.getloadavg()[0]:.2f}", flush=True)
        same_rows(tmp_path, arms, args.repeats)
        costs = step_costs(results, cache, exports, cells[0], args.max_steps, resets)
    medians = {arm: statistics.median(r) for arm, r in rates.items()}
    # past the startup (imports, simulator builds), N workers finish N episodes per episode time as measured inside
    steady = {arm: arm[0] * 3600 / statistics.median(inside[arm]) for arm in arms}
    for n, reset in arms:
        print(f"{n} worker(s), {reset} reset: median {medians[n, reset]:.0f} episodes/hour (wall, startup included); "
              f"median episode {statistics.median(inside[n, reset]):.1f} s inside its worker, "
              f"{steady[n, reset]:.0f} episodes/hour past the startup")
    for first, last in zip(arms, arms[1:]):
        if first[1] == last[1] or first[0] == last[0]:
            print(f"ratio {last[0]} worker(s) {last[1]} vs {first[0]} worker(s) {first[1]}: "
                  f"{medians[last] / medians[first]:.2f} (wall), {steady[last] / steady[first]:.2f} past the startup")
    for reset, c in costs.items():
        print(f"one in-process episode, {reset} reset ({c['steps']:.0f} steps, {c['episode']:.1f} s with its reset): "
              f"env reset {c['env reset']:.2f} s, env step {c['env step'] * 1000:.0f} ms, policy call "
              f"{c['policy call'] * 1000:.0f} ms (means a step)")
    print(f"machine after: {cpu()}")


def same_rows(tmp_path: Path, arms: list[tuple[int, str]], repeats: int) -> None:
    """Every arm's rows are the same episodes, success, steps and graded measures alike (seconds and command aside):
    print whether they are, a speed figure of rows that differ being no figure of the same work."""
    import polars as pl

    varying = ["seconds", "command"]
    tables = [pl.read_parquet(tmp_path / f"run{r}-w{n}-{reset}" / "rollouts.parquet").drop(varying).sort("episode_id")
              for r in range(repeats) for n, reset in arms]
    print(f"rows of every run equal: {all(t.equals(tables[0]) for t in tables[1:])}", flush=True)


if __name__ == "__main__":
    main()
