"""`graftcache rollout --workers N`: N episodes busy at once on this machine, each in a worker process of its own;
this module is the rollout's side of the team, graftcache.rollout.worker_process the worker's.

Why processes, started by spawn: MuJoCo's EGL context and torch's thread pools do not survive a fork, and threads
would share one GIL. Each worker builds one simulator (graftcache.rollout.libero.LiberoSimulator, whose env cache and
last loaded cell it keeps) and runs the episodes this process hands it, one at a time.

Startup: the team is started before this process asks for the request's episodes
(graftcache.rollout.roll_out.roll_out_started), so that the workers' imports and simulator builds overlap this
process's own (a simulator that says what its suites are: lerobot's LIBERO imports); workers left without an episode
are stopped once the episodes are known. One team serves the requests of one command in turn (the closed-loop demo's
two), so they start once.

Granularity: the episode, not the cell, so that a few cells of many episodes still keep every worker busy. This process
schedules, as for every team (graftcache.rollout.schedule.drive, this team its transport): a worker that finishes gets
the next episode of the cell it ran last (its policy stays loaded), else the episodes of a cell no worker is serving,
and only then joins another worker's cell. With many cells each worker keeps to its own and loads each policy once.

Exports: a worker exports a cell when it first runs one of its episodes (LiberoSimulator.export, reuse=True), which is
safe for concurrent writers: each writes a temporary folder and renames it in place, and the slower one keeps the
folder already there (graftcache.export.bundle.place). Since a fresh cell goes to one worker, two workers export one
cell only when more workers than cells are left: one export's time lost, never a wrong folder. Exporting every cell
here first would instead load each base policy in this process, one after the other, before any episode starts.

Rows: a worker writes each episode's video and row as the episode finishes (graftcache.rollout.record.record; appends to
the rollouts file are made under its lease, safe across processes) and sends back its report
(graftcache.rollout.episodes.EpisodeReport). Claims: this process holds them, as for every team
(graftcache.rollout.schedule.Scheduler): two rollouts sharing a file, of any --workers, never run one episode twice.

Failures: a worker's error is sent here and raised as one RolloutError line naming the run and episode; a worker that
dies (kill -9, out of memory) is one line naming the episode it was running. Either way the other workers are stopped
and the claims given back; every row written is whole and a rerun runs the missing episodes. Ctrl-C or SIGTERM here
stops every worker (graftcache.processes.stop: SIGTERM, then SIGKILL after a grace period, whatever the worker does
with SIGTERM); the workers ignore the terminal's SIGINT, so the stop is this process's one line. A kill -9 of this
process: the kernel sends each worker SIGKILL (Linux PR_SET_PDEATHSIG, graftcache.rollout.worker_process; elsewhere
the closed pipe ends it after its episode), this process's claims go stale with its pid, and a rerun runs the
episodes that were not written.

Determinism: an episode seeds its RNGs from its own seed and starts from its own init state, and its policy runs at
graftcache.rollout.simulator_setup.POLICY_THREADS torch threads whatever N, so N workers write the rows one would
(seconds and command aside).
"""

from __future__ import annotations

import multiprocessing
import os
import time
from collections.abc import Callable, Sequence
from contextlib import suppress
from dataclasses import dataclass
from multiprocessing.connection import Connection, wait
from multiprocessing.process import BaseProcess

from graftcache.errors import RolloutError
from graftcache.processes import WORKER_GRACE_S, sigint_ignored, sigterm_held, stop
from graftcache.rollout.episodes import Episode, EpisodeReport, Simulator, where
from graftcache.rollout.request import RolloutRequest
from graftcache.rollout.schedule import Job
from graftcache.rollout.worker_process import serve

#: how long workers told to finish get to close their simulators before they are stopped
CLOSE_S = 30.0


@dataclass
class _Worker:
    index: int
    process: BaseProcess
    conn: Connection
    running: Episode | None = None
    last: str | None = None  # the run_id of the cell it ran last (whose policy it holds)


def team_size(asked: int, log: Callable[[str], None]) -> int:
    """`asked` workers, at most one per CPU this process may run on, the cap said in one line: each worker is a
    simulator and a policy of its own, busy on a core, so more only share the cores and fill the memory. The team is
    started before the episodes are known; once they are, workers beyond them are stopped (`Workers.run`)."""
    cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    if asked <= cpus:
        return asked
    log(f"--workers {asked}: starting {cpus}, one per CPU this process may run on")
    return cpus


class Workers:
    """A rollout's team of `n` spawned worker processes (graftcache.rollout.teams.Team), started when built: each
    builds its simulator with `spawn` while the rollout builds its own (graftcache.rollout.roll_out.roll_out_started),
    so the imports and the simulators' builds overlap. The one loop hands them the missing episodes
    (graftcache.rollout.schedule.drive, this team its transport); `close` stops them."""

    def __init__(self, spawn: Callable[[], Simulator], n: int, req: RolloutRequest) -> None:
        self.workers = _start(n, spawn, req)  # those the loop hands episodes to (graftcache.rollout.schedule.Transport)
        self.idle = False  # every worker built and serving requests: set when one begins, cleared by a stop

    def begin(self, req: RolloutRequest, episodes: int, log: Callable[[str], None]) -> None:
        """Workers beyond `episodes` stopped at once; the others run the request's episodes, then wait for the next
        request (graftcache.rollout.teams.Team) or `close`. A failure stops them all (`stop`)."""
        self.workers, spare = self.workers[:episodes], self.workers[episodes:]
        _stop(spare)
        self.idle = True
        log(f"{len(self.workers)} worker processes, each with a simulator of its own")

    def send(self, worker: _Worker, job: Job) -> None:
        worker.conn.send(job)

    def receive(self, timeout: float | None) -> list[tuple[_Worker, EpisodeReport]]:
        """The reports the workers sent, waiting up to `timeout` for one; a worker's death (its pipe closed, its
        process ended) is raised, running or idle."""
        ready = wait([w.conn for w in self.workers] + [w.process.sentinel for w in self.workers], timeout=timeout)
        reports = []
        for worker in self.workers:
            if worker.conn in ready or worker.conn.poll():
                reports.append((worker, _receive(worker)))
            elif worker.process.sentinel in ready:
                raise RolloutError(_death(worker))
        return reports

    def stop(self) -> None:
        """Stopped or failed: no worker outlives the loop (nor writes a row once its cell's claim is given back)."""
        self.idle = False
        _stop(self.workers)

    def close(self) -> None:
        """Every worker stopped: idle ones first told to finish and given their time to close their simulators
        (CLOSE_S); a team that never ran or failed (a stop, an error: nothing to wait for) at once."""
        try:
            if self.idle:
                _finish(self.workers)
        finally:
            _stop(self.workers)


def _receive(worker: _Worker) -> EpisodeReport:
    """A worker's report of its episode; its failure raised as one line naming the episode."""
    try:
        kind, *body = worker.conn.recv()
    except (EOFError, OSError):
        raise RolloutError(_death(worker)) from None
    if kind == "broken":
        raise RolloutError(f"rollout worker {worker.index} (pid {worker.process.pid}) could not build its simulator: "
                           f"{body[0]}")
    if kind == "failed":
        raise RolloutError(f"{where(worker.running)}: {body[0]} (rollout worker {worker.index}, pid "
                           f"{worker.process.pid})")
    return body[0]


def _death(worker: _Worker) -> str:
    worker.process.join(WORKER_GRACE_S)  # its pipe closes a moment before it can be reaped
    code = worker.process.exitcode
    how = f"killed by signal {-code}" if code is not None and code < 0 else f"exit code {code}"
    doing = f"while running {where(worker.running)}" if worker.running is not None else "while idle"
    return (f"rollout worker {worker.index} (pid {worker.process.pid}) died ({how}) {doing}; the episodes written "
            "are kept: rerun the command to run the others")


def _start(n: int, spawn: Callable[[], Simulator], req: RolloutRequest) -> list[_Worker]:
    """n spawned workers (graftcache.rollout.worker_process.serve), each with its end of a pipe. They start with
    SIGINT ignored (graftcache.processes.sigint_ignored), so a Ctrl-C at the terminal stops them through this process
    only, and a SIGTERM here waits until each has started (graftcache.processes.sigterm_held)."""
    context = multiprocessing.get_context("spawn")
    team = []
    with sigint_ignored():
        for i in range(n):
            here, there = context.Pipe()
            process = context.Process(target=serve, args=(there, spawn, req.rollouts, req.command, os.getpid()),
                                      name=f"graftcache-rollout-{i}", daemon=True)
            with sigterm_held():
                process.start()
            there.close()
            team.append(_Worker(i, process, here))
    return team


def _finish(team: Sequence[_Worker]) -> None:
    """Every episode written: tell the workers to close their simulators and wait for them (CLOSE_S at most)."""
    for worker in team:
        with suppress(OSError):
            worker.conn.send(None)
    deadline = time.monotonic() + CLOSE_S
    for worker in team:
        worker.process.join(max(0.0, deadline - time.monotonic()))


def _stop(team: Sequence[_Worker]) -> None:
    """Every live worker stopped (graftcache.processes.stop), every pipe closed."""
    stop([w.process for w in team])
    for worker in team:
        worker.conn.close()
