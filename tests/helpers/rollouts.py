"""Fake simulators: `Scripted`, whose outcomes follow from each episode (the rollout tests'), and one for `graftcache
rollout --workers N` (graftcache.rollout.workers): importable by name, so that a spawned worker process can build it
(the team pickles its factory by reference), and leaving traces on disk, since what a worker ran is not in the test's
process."""

from __future__ import annotations

import importlib.metadata
import os
import signal
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import polars as pl
from tqdm import tqdm

import graftcache
from graftcache.hashing import sha256_json
from graftcache.rollout import rollouts_file
from graftcache.rollout.episodes import Episode, Outcome, Suite
from graftcache.rollout.graded import Graded
from graftcache.rollout.request import RolloutRequest
from graftcache.rollout.roll_out import roll_out
from graftcache.rollout.select import select
from helpers.tables import write_results

#: (run_id, task_index, episode) of an episode
Where = tuple[str, int, int]
#: what may differ between two runs of the same episodes
VARYING = ["seconds", "command"]


def paced_request(folder: Path, **over: Any) -> RolloutRequest:
    """The team tests' request: helpers.tables' results (written into `folder` once), their top cell of each
    (backbone, encoder) on libero_object, tasks 0 and 3, 2 episodes each, seed 7; `over` replaces fields."""
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "results.parquet"
    if not path.exists():
        write_results(path)
    fields = {"results": path, "rollouts": folder / "rollouts.parquet", "top": 1, "suites": ("libero_object",),
              "tasks": (0, 3), "episodes_per_task": 2, "seed": 7, "command": "graftcache rollout results.parquet"}
    return RolloutRequest(**{**fields, **over})


def rolled(req: RolloutRequest, sim: Any, log: Callable[[str], None], **team: Any) -> pl.DataFrame:
    """`roll_out` of `req` with its rows selected as the command selects them (graftcache.rollout.select.select),
    both saying what they do in `log`."""
    return roll_out(select(req, log=log), sim, log, **team)


class Scripted:
    """A Simulator whose episode k succeeds when its seed is even, in k + 3 steps, came within 0.1 * (k + 1) m of its
    target and, when perturbed by up to P m, slid it by (P / 2, -P / 4); it counts the episodes it ran.
    `stop_after`: raise after that many episodes (a run killed mid-way). `videos`: record steps + 1 frames of 16x16
    at 10 fps, as the LIBERO simulator's render callback would. A subclass scripts other outcomes (`outcome`)."""

    def __init__(self, stop_after: int | None = None, videos: bool = False) -> None:
        self.ran: list[Episode] = []
        self.stop_after = stop_after
        self.videos = videos

    def suite(self, name: str) -> Suite:
        return Suite(n_tasks=10, max_steps=280)

    def run(self, row: Mapping[str, Any], episodes: Sequence[Episode]) -> Iterator[Outcome]:
        for e in episodes:
            if self.stop_after is not None and len(self.ran) == self.stop_after:
                raise KeyboardInterrupt
            self.ran.append(e)
            yield self.outcome(row, e)

    def outcome(self, row: Mapping[str, Any], e: Episode) -> Outcome:
        steps = e.episode + 3
        frames = np.full((steps + 1, 16, 16, 3), 40 * e.episode, np.uint8) if self.videos else None
        graded = Graded(target="alphabet_soup_1", min_target_distance_m=0.1 * (e.episode + 1),
                        final_target_distance_m=0.3, target_lift_m=0.0, grasped=e.episode == 1, goal_fraction=0.0)
        return Outcome(success=e.seed % 2 == 0, steps=steps, seconds=0.5, init_state=e.episode, frames=frames,
                       fps=10 if self.videos else None, graded=graded,
                       target_offset_m=(e.perturbation_m / 2, -e.perturbation_m / 4), kernels="scripted")


class Paced:
    """A Simulator whose episode k succeeds when its seed is even, in k + 3 steps (test_rollout.py's Scripted), taking
    `delay` seconds. Each process that builds one writes its pid to `traces`/pids/, and each episode it runs as a line
    "pid run_id task episode" to `traces`/ran-<pid>.txt. `fail`: that episode raises; `die`: its process kills itself
    with SIGKILL there (a worker killed mid-episode); `spin`: there it enters hf-libero's own reset loop with a scene
    that never places (`spin_in_reset`), as a worker whose scene will not build does, and writes
    `traces`/spinning-<pid>; `debris`: there it builds a `HalfBuilt` that a stop cuts short, writing
    `traces`/building-<pid>. Each episode steps under a disabled tqdm bar, as lerobot's rollout loop does."""

    def __init__(self, traces: Path, delay: float = 0.0, fail: Where | None = None, die: Where | None = None,
                 spin: Where | None = None, debris: Where | None = None) -> None:
        self.traces, self.delay, self.fail, self.die, self.spin, self.debris = traces, delay, fail, die, spin, debris
        (traces / "pids").mkdir(parents=True, exist_ok=True)
        (traces / "pids" / str(os.getpid())).touch()

    def suite(self, name: str) -> Suite:
        return Suite(n_tasks=10, max_steps=280)

    def run(self, row: Mapping[str, Any], episodes: Sequence[Episode]) -> Iterator[Outcome]:
        for e in episodes:
            at = (e.run_id, e.task_index, e.episode)
            if at == self.die:
                os.kill(os.getpid(), signal.SIGKILL)
            tqdm(total=1, disable=True).close()  # its class's lock: a multiprocessing semaphore unless set
            if at == self.spin:
                spin_in_reset(self.traces / f"spinning-{os.getpid()}")
            if at == self.debris:
                HalfBuilt(self.traces / f"building-{os.getpid()}")
            if at == self.fail:
                raise RuntimeError("the simulator broke\nat its second line")
            time.sleep(self.delay)
            with open(self.traces / f"ran-{os.getpid()}.txt", "a") as f:
                f.write(f"{os.getpid()} {e.run_id} {e.task_index} {e.episode}\n")
            yield Outcome(success=e.seed % 2 == 0, steps=e.episode + 3, seconds=self.delay, init_state=e.episode)


class HalfBuilt:
    """As robosuite's MjRenderContext: `__del__` frees what `__init__` sets up last, so an `__init__` that a stop cut
    short leaves an object whose `__del__` raises (Python prints it as "Exception ignored in ...")."""

    def __init__(self, marker: Path) -> None:
        marker.touch()
        while True:  # building, until stopped
            time.sleep(0.05)
        self.context = object()

    def __del__(self) -> None:
        del self.context


def spin_in_reset(marker: Path) -> None:
    """hf-libero's ControlEnv.reset, the real loop (`while not success: try: reset ... finally: continue`), over a
    scene whose every placement fails: it never returns, and its `finally: continue` swallows whatever a signal's
    handler raises in it (a KeyboardInterrupt, graftcache.processes.Terminated). `marker` is written once the loop
    runs (hf-libero's imports take seconds, and a stop during them ends the process as any other would)."""
    from libero.libero.envs.env_wrapper import ControlEnv
    from robosuite.utils.errors import RandomizationError

    def unplaceable() -> None:
        marker.touch()
        time.sleep(0.01)  # a placement's work, so the spin leaves the shared cores some room
        raise RandomizationError("cannot place all objects")

    ControlEnv.reset(SimpleNamespace(env=SimpleNamespace(reset=unplaceable)))


def ran(traces: Path) -> list[tuple[int, str, int, int]]:
    """Every episode the Paced simulators writing to `traces` ran: (pid, run_id, task, episode)."""
    lines = [ln.split() for f in sorted(traces.glob("ran-*.txt")) for ln in f.read_text().splitlines()]
    return [(int(pid), run, int(task), int(k)) for pid, run, task, k in lines]


def pids(traces: Path) -> list[int]:
    """The processes that built a Paced simulator writing to `traces`."""
    return sorted(int(p.name) for p in (traces / "pids").iterdir()) if (traces / "pids").is_dir() else []


def paced_rows(run_ids: Sequence[str], tasks: Sequence[int], episodes: int, seed: int) -> pl.DataFrame:
    """The rows a Paced simulator's episodes give, from its definition (episode k: seed + k, success when the seed
    is even, k + 3 steps, init state k) and the rollouts schema by hand, `seconds` and `command` aside: nothing
    graded, no video, no perturbation."""
    rows = []
    for run_id, task, k in ((r, t, k) for r in run_ids for t in tasks for k in range(episodes)):
        key = {"run_id": run_id, "suite": "libero_object", "task_index": task, "episode": k, "seed": seed + k,
               "max_steps": 280}
        rows.append({"episode_id": sha256_json(key)[:16], "format_version": rollouts_file.FORMAT_VERSION, **key,
                     "init_state": k,
                     "success": (seed + k) % 2 == 0, "steps": k + 3, "video": None, "target": None,
                     "perturbation_m": 0.0, "target_offset_x_m": None, "target_offset_y_m": None,
                     "min_target_distance_m": None, "final_target_distance_m": None, "target_lift_m": None,
                     "grasped": None, "goal_fraction": None, "kernels": None,
                     "lerobot_version": importlib.metadata.version("lerobot"),
                     "graftcache_version": graftcache.__version__})
    schema = {c: t for c, t in rollouts_file.SCHEMA.items() if c not in ("seconds", "command")}
    return pl.DataFrame(rows, schema=schema).sort("episode_id")
