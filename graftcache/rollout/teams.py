"""What runs a rollout's episodes (a team, `Team`) and the team of one (`InProcess`): this process's simulator,
running each episode as the one loop sends it (graftcache.rollout.schedule.drive). The other teams are worker
processes (graftcache.rollout.workers.Workers) and Ray actors (graftcache.executors.ray_rollout.Actors)."""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Protocol

from graftcache.rollout.episodes import Episode, EpisodeReport, Simulator
from graftcache.rollout.record import run_one
from graftcache.rollout.request import RolloutRequest
from graftcache.rollout.schedule import CLAIM_POLL_S, Job, Transport, Worker


class Team(Transport, Protocol):
    """Runs a rollout's missing episodes, each worker with a simulator of its own: spawned processes on this
    machine (graftcache.rollout.workers.Workers, `--workers N`) or Ray actors (graftcache.executors.ray_rollout.Actors,
    `--executor ray`), as an executor starts them (graftcache.executors.Executor.rollout_team), else this process's
    team of one (InProcess); to the one loop (graftcache.rollout.schedule.drive) each is the transport. A team starts
    when built, so its simulators build while this process asks its simulator for the request's episodes; it gets
    every episode written. It serves requests one after another until closed
    (graftcache.rollout.roll_out.roll_out_started), so a command of several requests pays for one start-up."""

    def begin(self, req: RolloutRequest, episodes: int, log: Callable[[str], None]) -> None:
        """Ready for `req`'s `episodes` missing episodes, which the one loop sends next: workers beyond them are
        ended at once (the team is smaller for the requests that follow)."""

    def close(self) -> None:
        """Every worker stopped; nothing of the team outlives it."""


@dataclass
class _Here:
    """The team of one's worker (graftcache.rollout.schedule.Worker)."""

    running: Episode | None = None
    last: str | None = None


class InProcess:
    """The team of one (`roll_out` without a team): this process's simulator runs each episode as it is sent, so
    episodes go through the loop the other teams' do (graftcache.rollout.schedule.drive). An error of the simulator
    is raised as it is."""

    def __init__(self, sim: Simulator, req: RolloutRequest) -> None:
        self.sim, self.rollouts, self.command = sim, req.rollouts, req.command
        self.workers: Sequence[Worker] = (_Here(),)
        self.reports: list[tuple[Worker, EpisodeReport]] = []

    def begin(self, req: RolloutRequest, episodes: int, log: Callable[[str], None]) -> None:
        """Nothing to end: the one worker is this process."""

    def send(self, worker: Worker, job: Job) -> None:
        row, episode = job
        self.reports.append((worker, run_one(self.sim, row, episode, self.rollouts, self.command)))

    def receive(self, timeout: float | None) -> list[tuple[Worker, EpisodeReport]]:
        if not self.reports:  # only cells another rollout holds are left
            pause(timeout)
        reports, self.reports = self.reports, []
        return reports

    def stop(self) -> None:
        """Nothing runs once the loop has stopped: each episode ran within `send`."""

    def close(self) -> None:
        """Nothing to stop: the simulator is its caller's."""


def pause(timeout: float | None) -> None:
    """A team's wait when nothing of its own can end it: `timeout` (a poll for another rollout's claims)."""
    time.sleep(CLAIM_POLL_S if timeout is None else timeout)
