"""The ray executor's rollout: a rollout's missing episodes run by Ray actors, each holding one simulator.

Why actors, not a task per episode: a simulator's start (lerobot's LIBERO imports, the env's build and first reset)
and a cell's policy load take longer than a short episode; an actor pays them once and keeps its envs and the cell it
ran last, as a `--workers` process does (graftcache/rollout/workers.py). The actors are created when the team is built,
before the driver asks for the request's episodes, so their simulators build meanwhile. The driver schedules as for
every team, through graftcache.rollout.schedule.drive with this team its transport: an actor that finishes gets the
next episode of its cell, else a cell no actor serves (claimed without waiting, graftcache.results.claims.cell_claim),
and only then joins another's cell.

Rows: an actor writes the episode's video whole (graftcache.rollout.record.with_video) and returns its row; the driver
appends it as the call finishes. So the rows are those of the local executor for the same episodes (an episode seeds
itself and runs its policy on graftcache.rollout.simulator_setup.POLICY_THREADS threads; seconds aside), a driver
killed mid-way has written whole rows only (Ray ends the actors of a driver that is gone, and the claims go stale with
it), and a rerun runs the missing episodes. Every node must see the results file, its run folders and caches (the actors
export the cells) and the rollouts file's folder (videos, exports) at the same paths, as for fitting.

Failures: an error inside an actor is one RolloutError line naming the run and episode (and the actor); an actor
whose process or node dies is restarted and its episode run again, up to `--max-retries` times, then one line naming
the episode.
"""

from __future__ import annotations

import os
import socket
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import ray

from graftcache.errors import RolloutError
from graftcache.executors import Log
from graftcache.executors.ray_cluster import connect, result, slots, task_options
from graftcache.requests import ExecutorSettings
from graftcache.rollout.episodes import Episode, EpisodeReport, Simulator, where
from graftcache.rollout.record import append, with_video
from graftcache.rollout.request import RolloutRequest
from graftcache.rollout.schedule import Job, one_line
from graftcache.rollout.teams import pause


class SimulatorHost:
    """One actor's simulator, built as the actor starts; `run` runs one episode on it, writes its video and returns
    its row (run as `SimulatorActor`)."""

    def __init__(self, spawn: Callable[[], Simulator], rollouts: Path, command: str, index: int) -> None:
        self.rollouts, self.command, self.index = rollouts, command, index
        self.sim: Simulator | None = None
        self.broken = ""
        try:
            self.sim = spawn()
        except Exception as e:  # said by the first episode handed here, naming the actor
            self.broken = one_line(e)

    def run(self, row: Mapping[str, Any], episode: Episode) -> dict[str, Any]:
        if self.sim is None:
            raise RolloutError(f"ray actor {self.index} ({self._at()}) could not build its simulator: {self.broken}")
        try:
            (outcome,) = self.sim.run(row, [episode])
            return with_video(self.rollouts, self.command, episode, outcome)
        except Exception as e:
            raise RolloutError(f"{where(episode)}: {one_line(e)} (ray actor {self.index}, {self._at()})") from None

    @staticmethod
    def _at() -> str:
        return f"pid {os.getpid()} on {socket.gethostname()}"


#: The Ray actor of `SimulatorHost`, kept apart so that cloudpickle ships the class by reference (see ray_fit).
SimulatorActor = ray.remote(SimulatorHost)


@dataclass
class _Actor:
    """An actor as the scheduler sees it (graftcache.rollout.schedule.Worker)."""

    index: int
    handle: Any
    running: Episode | None = None
    last: str | None = None


class Actors:
    """A rollout's team of Ray actors (graftcache.rollout.teams.Team), created when built: `n` of them, at most (and by
    default) as many as the cluster runs at once for `--cpus-per-task` / `--gpus-per-task`."""

    def __init__(self, req: RolloutRequest, spawn: Callable[[], Simulator], n: int | None,
                 settings: ExecutorSettings, log: Log) -> None:
        connect(settings, log)
        placed = task_options(settings, req.device)  # GPUs for an actor whose policy runs on CUDA
        fits = slots(placed)
        if n and n > fits:  # an actor that cannot be placed would hold its first episode forever
            log(f"ray: --workers {n}, but the cluster holds {fits} such actor(s) at once: {fits}")
        n = min(n or fits, fits)
        options = {"num_cpus": placed["num_cpus"], "num_gpus": placed["num_gpus"],
                   "max_restarts": settings.max_retries, "max_task_retries": settings.max_retries}
        log(f"ray: {n} simulator actor(s), {placed['num_gpus']:g} GPU and {placed['num_cpus']:g} CPU each")
        rollouts = req.rollouts.absolute()
        # those the loop hands episodes to (graftcache.rollout.schedule.Transport)
        self.workers = [_Actor(i, SimulatorActor.options(**options).remote(spawn, rollouts, req.command, i))
                        for i in range(n)]
        self.rollouts = req.rollouts
        self.calls: dict[ray.ObjectRef, _Actor] = {}

    def begin(self, req: RolloutRequest, episodes: int, log: Log) -> None:
        """Actors beyond `episodes` ended at once, the others kept for the next request
        (graftcache.rollout.teams.Team) until `close`; the loop hands them the episodes, an episode per call, and each
        row is appended here as its call finishes (`receive`)."""
        self.workers, spare = self.workers[:episodes], self.workers[episodes:]
        for actor in spare:
            ray.kill(actor.handle, no_restart=True)
        self.rollouts, self.calls = req.rollouts, {}
        log(f"ray: {len(self.workers)} simulator actor(s) running {episodes} episode(s)")

    def send(self, worker: _Actor, job: Job) -> None:
        self.calls[worker.handle.run.remote(*job)] = worker

    def receive(self, timeout: float | None) -> list[tuple[_Actor, EpisodeReport]]:
        """The calls finished, each row appended here as it comes (the actor wrote its video)."""
        if not self.calls:  # every cell left is another rollout's for now
            pause(timeout)
            return []
        ready, _ = ray.wait(list(self.calls), num_returns=1, timeout=timeout)
        reports = []
        for ref in ready:
            actor = self.calls.pop(ref)
            assert actor.running is not None
            row = result(ref, where(actor.running))
            append(self.rollouts, [row])
            reports.append((actor, EpisodeReport.of(row)))
        return reports

    def stop(self) -> None:
        """Nothing here: the actors are ended by `close`, and a call in flight writes no row (the driver does)."""

    def close(self) -> None:
        for actor in self.workers:
            ray.kill(actor.handle, no_restart=True)
