"""gpu_check's closed-loop stage (11): what `graftcache rollout --workers N` costs on the device's policy and renderer
against the CPU path of the same machine, on the same episodes.

Each arm is the whole command a user runs (`python -m graftcache rollout ... --workers N --device D`, a fresh process
with MUJOCO_GL set, into a rollouts file of its own, the cells' exports copied beside it), over
benchmarks/closed_loop_cells.py's two tiny cells on libero_object task 0: the device path (policy on `--device`,
MuJoCo through `device_gl`) and the CPU path (policy on the CPU, MuJoCo through `cpu_gl`). Each arm records its
wall time and episodes per hour (imports and simulator builds included: what a user waits for), the median episode
inside its worker and the rate past the startup (N workers finish N episodes per episode time), the kernels its rows
record, and which renderer MuJoCo's context reports under its MUJOCO_GL (a GPU machine without Mesa renders the
CPU path's frames on the GPU too: the renderer says so). The rows of every arm are then compared with the first
arm's, seconds, command and kernels aside: on one set of kernels they must be equal (an episode is decided by its
key), across kernels they may drift, and the JSON says by how much against TOLERANCE_M.
"""

from __future__ import annotations

import os
import statistics
import subprocess
import sys
import time
from dataclasses import dataclass
from functools import cache
from pathlib import Path

from closed_loop_cells import RESULTS, SUITE, prepared, rollout_argv

#: the rows' columns that do not decide or describe the episode: left out of the comparison
VARYING = ("seconds", "command", "kernels")
#: graded distances of one episode on other kernels within this many metres count as the same episode: a tenth of the
#: smallest differences paired episodes resolved between encoders (docs/measured.md), below any verdict's reach
TOLERANCE_M = 0.002
DISTANCES = ("min_target_distance_m", "final_target_distance_m", "target_lift_m")
#: what MuJoCo's GL context reports, asked in a fresh process under an arm's MUJOCO_GL
RENDERER = ("import mujoco; from OpenGL import GL; c = mujoco.GLContext(64, 64); c.make_current(); "
            "print(GL.glGetString(GL.GL_VENDOR).decode(), '/', GL.glGetString(GL.GL_RENDERER).decode()); c.free()")


@dataclass(frozen=True)
class Arm:
    """One measured rollout: `name` (device or cpu), the policy's `device`, MuJoCo's `gl` and the `workers`."""

    name: str
    device: str
    gl: str
    workers: int

    @property
    def key(self) -> str:
        return f"{self.name}_w{self.workers}"

    def env(self) -> dict[str, str]:
        """The process environment of this arm: MuJoCo's backend, and PyOpenGL's platform where it is EGL or
        OSMesa (PyOpenGL picks GLX otherwise, which has no display here)."""
        env = {**os.environ, "MUJOCO_GL": self.gl, "HF_HUB_OFFLINE": "1"}
        if self.gl in ("egl", "osmesa"):
            env["PYOPENGL_PLATFORM"] = self.gl
        return env


def arms(device: str, workers: list[int], cpu_gl: str, device_gl: str) -> list[Arm]:
    """The device path then the CPU path at each worker count (the device's first: it is the figure asked for)."""
    return [Arm(name, d, gl, n) for n in workers
            for name, d, gl in (("device", device, device_gl), ("cpu", "cpu", cpu_gl))]


@cache
def renderer(gl: str) -> str:
    """The GL vendor and renderer MuJoCo gets under MUJOCO_GL `gl`, or why none (one line); asked once a backend."""
    env = Arm("", "cpu", gl, 1).env()
    done = subprocess.run([sys.executable, "-c", RENDERER], env=env, capture_output=True, text=True, timeout=60)
    if done.returncode:
        return "unavailable: " + (done.stderr.strip().splitlines() or ["no error output"])[-1][:300]
    return done.stdout.strip()


def roll_out(arm: Arm, cells: Path, folder: Path, episodes: int, steps: int, timeout_s: float) -> dict:
    """Run `arm` into `folder`/rollouts.parquet: its measures (the rows stay in the file)."""
    import polars as pl

    run_ids = pl.read_parquet(cells / RESULTS).filter(pl.col("suite") == SUITE)["run_id"].to_list()
    rollouts = prepared(cells, folder)
    argv = rollout_argv(cells, rollouts, episodes=episodes, steps=steps, workers=arm.workers,
                        flags=("--run-ids", ",".join(run_ids), "--device", arm.device))
    t0 = time.perf_counter()
    done = subprocess.run(argv, env=arm.env(), capture_output=True, text=True, timeout=timeout_s)
    wall = time.perf_counter() - t0
    if done.returncode:
        raise RuntimeError((done.stderr.strip().splitlines() or [f"exit {done.returncode}"])[-1])
    rows = pl.read_parquet(rollouts)
    median = statistics.median(rows["seconds"].to_list())
    return {"policy_device": arm.device, "mujoco_gl": arm.gl, "workers": arm.workers, "cells": len(run_ids),
            "episodes": rows.height, "steps": steps, "wall_s": round(wall, 1),
            "episodes_per_hour": round(rows.height / wall * 3600, 1), "median_episode_s": round(median, 3),
            "steady_episodes_per_hour": round(arm.workers * 3600 / median, 1),
            "kernels": sorted(rows["kernels"].unique().to_list())}


def compared(rows: Path, first: Path) -> dict:
    """How the rows at `rows` differ from those at `first`, episode by episode (seconds, command, kernels aside):
    whether every one is equal, how many agree on success and steps, the largest graded distance between them."""
    import polars as pl

    a, b = (pl.read_parquet(p).drop(VARYING).sort("episode_id") for p in (rows, first))
    if a["episode_id"].to_list() != b["episode_id"].to_list():
        raise RuntimeError(f"{rows}: other episodes than {first}'s")
    drift = {c: float((a[c] - b[c]).abs().max() or 0.0) for c in DISTANCES}
    same_outcome = int(((a["success"] == b["success"]) & (a["steps"] == b["steps"])).sum())
    return {"against": first.parent.name, "equal": a.equals(b), "same_success_and_steps": same_outcome,
            "episodes": a.height, "max_drift_m": drift, "tolerance_m": TOLERANCE_M,
            "within_tolerance": same_outcome == a.height and max(drift.values()) <= TOLERANCE_M}


def stage_closed_loop(report, device: str, cells: Path | None, scratch: Path, workers: list[int], episodes: int,
                      steps: int, cpu_gl: str, device_gl: str) -> None:
    """Stage 11 into `report` (gpu_check.Report): each arm's measures and rows compared with the first arm's, and
    the device path's rate against the CPU path's at each worker count. `cells`: benchmarks/closed_loop_cells.py's
    folder; None: fitted into `scratch` first (a CPU dry run; a GPU image lacks the data layer)."""
    stage = "11_closed_loop"
    if cells is None:
        with report.check(stage, "cells", need_s=120) as out:
            if out is None:
                return
            from closed_loop_cells import fit_cells

            cells = scratch / "closed-loop-cells"
            fit_cells(cells)
            out["fitted_into"] = str(cells)
        if report.data["stages"][stage]["cells"]["status"] != "ok":
            return
    first: Path | None = None  # the first arm's rows, which every later arm's are compared with
    for arm in arms(device, workers, cpu_gl, device_gl):
        with report.check(stage, arm.key, need_s=60) as out:
            if out is None:
                continue
            folder = scratch / "closed-loop" / arm.key
            out["renderer"] = renderer(arm.gl)
            out.update(roll_out(arm, cells, folder, episodes, steps, timeout_s=max(report.left(), 60.0)))
            if first is not None:
                out["rows"] = compared(folder / "rollouts.parquet", first)
            first = first or folder / "rollouts.parquet"
    entries = report.data["stages"][stage]
    for n in workers:
        fast, slow = entries.get(f"device_w{n}", {}), entries.get(f"cpu_w{n}", {})
        if fast.get("status") == slow.get("status") == "ok":
            entries[f"ratio_w{n}"] = {
                "status": "ok", "episodes_per_hour": round(fast["episodes_per_hour"] / slow["episodes_per_hour"], 2),
                "steady_episodes_per_hour": round(fast["steady_episodes_per_hour"] / slow["steady_episodes_per_hour"],
                                                  2)}
    report.write()
