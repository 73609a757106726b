"""`graftcache rollout --workers N`: N episodes busy at once on this machine, each in a worker process of its own.

Why processes, started by spawn: MuJoCo's EGL context and torch's thread pools do not survive a fork, and threads
would share one GIL. Each worker builds one simulator (graftcache.rollout.libero.LiberoSimulator, whose env cache and
last loaded cell it keeps) and runs the episodes this process hands it, one at a time.

Startup: the team is started before this process plans (graftcache.rollout.run.roll_out_started), so that the
workers' imports and simulator builds overlap this process's own (a simulator to plan with: lerobot's LIBERO imports)
and its planning; workers left without an episode are stopped when the plan is known. One team serves the requests
of one command in turn (the closed-loop demo's two), so they start once.

Granularity: the episode, not the cell, so that a few cells of many episodes still keep every worker busy. This process
schedules: a worker that finishes gets the next episode of the cell it ran last (its policy stays loaded), else the
episodes of a cell no worker is serving (one already claimed, else one it claims now), and only then joins another
worker's cell. With many cells each worker keeps to its own and loads each policy once.

Exports: a worker exports a cell when it first runs one of its episodes (LiberoSimulator.export, reuse=True), which is
safe for concurrent writers: each writes a temporary folder and renames it in place, and the slower one keeps the
folder already there (graftcache.export.bundle.place). Since a fresh cell goes to one worker, two workers export one
cell only when more workers than cells are left: one export's time lost, never a wrong folder. Exporting every cell
here first would instead load each base policy in this process, one after the other, before any episode starts.

Rows: a worker writes each episode's video and row as the episode finishes (graftcache.rollout.run.record; appends to
the rollouts file are made under its lease, safe across processes). Claims: this process holds the claim of each cell
it has episodes of (graftcache.results.claims.cell_claim, as the one-process rollout does), taken when it first needs
the cell and without waiting (a cell another rollout holds is left to it and tried again later; once taken, what the
file then holds is read again) and given back once the cell's last episode is written: two rollouts sharing a file, of
any --workers, never run one episode twice.

Failures: a worker's error is sent here and raised as one RolloutError line naming the run and episode; a worker that
dies (kill -9, out of memory) is one line naming the episode it was running. Either way the other workers are stopped
and the claims given back; every row written is whole and a rerun runs the missing episodes. Ctrl-C or SIGTERM here
stops every worker (graftcache.processes.stop: SIGTERM, then SIGKILL after a grace period, whatever the worker does
with SIGTERM); the workers ignore the terminal's SIGINT, so the stop is this process's one line. A kill -9 of this
process: the kernel sends each worker SIGKILL (Linux PR_SET_PDEATHSIG; elsewhere the closed pipe ends it after its
episode), this process's claims go stale with its pid, and a rerun runs the episodes that were not written.

Determinism: an episode seeds its RNGs from its own seed and starts from its own init state, and its policy runs at
graftcache.rollout.libero.POLICY_THREADS torch threads whatever N, so N workers write the rows one would (seconds and
command aside).
"""

from __future__ import annotations

import ctypes
import multiprocessing
import os
import signal
import sys
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager, suppress
from dataclasses import dataclass
from multiprocessing.connection import Connection, wait
from multiprocessing.process import BaseProcess
from pathlib import Path
from typing import Any

from graftcache.errors import GraftcacheError, RolloutError
from graftcache.file_lease import FileLease
from graftcache.processes import WORKER_GRACE_S, Terminated, stop
from graftcache.results.claims import cell_claim
from graftcache.rollout import table
from graftcache.rollout.episodes import Episode, Simulator
from graftcache.rollout.run import RolloutRequest, record, summary

#: how often cells that other rollouts hold are tried again while nothing else is left to hand out
CLAIM_POLL_S = 1.0
#: how long workers told to finish get to close their simulators before they are stopped
CLOSE_S = 30.0
PR_SET_PDEATHSIG = 1  # linux/prctl.h


@dataclass
class _Cell:
    """A cell's episodes as this process hands them out, and what its finished ones gave (its summary line)."""

    row: Mapping[str, Any]
    todo: deque[Episode]
    claim: FileLease | None = None
    closed: bool = False
    running: int = 0
    told: bool = False  # whether the wait for another rollout's claim of it was said
    done: int = 0
    wins: int = 0
    steps: int = 0
    seconds: float = 0.0
    videos: int = 0


@dataclass
class _Worker:
    index: int
    process: BaseProcess
    conn: Connection
    running: Episode | None = None
    last: str | None = None  # the run_id of the cell it ran last (whose policy it holds)


def where(episode: Episode) -> str:
    return (f"run {episode.run_id}, {episode.suite} task {episode.task_index} episode {episode.episode} "
            f"(seed {episode.seed})")


def one_line(e: BaseException) -> str:
    """An error as one line: a GraftcacheError's own words, anything else with its type."""
    first = (str(e).strip().splitlines() or [""])[0]
    return first if isinstance(e, GraftcacheError) else f"{type(e).__name__}: {first}".rstrip(": ")


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
    """A rollout's team of `n` spawned worker processes (graftcache.rollout.run.Team), started when built: each builds
    its simulator with `spawn` while the rollout builds its own to plan (graftcache.rollout.run.roll_out_started), so
    the imports and the simulators' builds overlap. `run` hands them the missing episodes; `close` stops them."""

    def __init__(self, spawn: Callable[[], Simulator], n: int, req: RolloutRequest) -> None:
        self.team = _start(n, spawn, req)
        self.idle = False  # every worker built and waiting, after a request that ended well

    def run(self, req: RolloutRequest, rows: Mapping[str, Mapping[str, Any]], missing: Sequence[Episode], bar: Any,
            log: Callable[[str], None]) -> None:
        """Run `missing` (episodes of the cells `rows` holds by run_id); `bar` advances by one per episode written or
        found written. Workers beyond the number of episodes are stopped at once; the others wait for the next
        request (graftcache.rollout.run.Team) or `close`. A failure stops them all."""
        cells = cells_of(rows, missing)
        self.team, spare = self.team[: len(missing)], self.team[len(missing):]
        _stop(spare)
        busy, self.idle = self.team, False
        log(f"{len(busy)} worker processes, each with a simulator of its own")
        scheduler = Scheduler(req, cells, bar, log)
        try:
            while not all(c.closed for c in cells.values()):
                for worker in busy:
                    if worker.running is None and (job := scheduler.dispatch(worker)) is not None:
                        worker.conn.send(job)
                if all(c.closed for c in cells.values()):  # another rollout wrote what was left: no report is owed
                    break
                running = any(w.running is not None for w in busy)
                ready = wait([w.conn for w in busy] + [w.process.sentinel for w in busy],
                             timeout=None if running and not scheduler.waiting() else CLAIM_POLL_S)
                for worker in busy:
                    if worker.conn in ready or worker.conn.poll():
                        scheduler.finished(worker, _receive(worker))
                    elif worker.process.sentinel in ready:
                        raise RolloutError(_death(worker))
        except BaseException:  # stopped or failed: no worker outlives the loop
            _stop(busy)
            raise
        finally:  # and no claim is left behind, also when a stop is raised again while the workers are reaped
            scheduler.release()  # (graftcache.cli.signals._Stop)
        self.idle = True

    def close(self) -> None:
        """Every worker stopped: idle ones first told to finish and given their time to close their simulators
        (CLOSE_S); a team that never ran or failed (a stop, an error: nothing to wait for) at once."""
        try:
            if self.idle:
                _finish(self.team)
        finally:
            _stop(self.team)


def cells_of(rows: Mapping[str, Mapping[str, Any]], missing: Sequence[Episode]) -> dict[str, _Cell]:
    """The missing episodes by cell, in the order of their first episode."""
    return {run_id: _Cell(rows[run_id], deque(e for e in missing if e.run_id == run_id))
            for run_id in dict.fromkeys(e.run_id for e in missing)}


class Scheduler:
    """Which episode an idle worker runs next (see the module docstring), and the bookkeeping of finished ones."""

    def __init__(self, req: RolloutRequest, cells: dict[str, _Cell], bar: Any, log: Callable[[str], None]) -> None:
        self.req, self.cells, self.bar, self.log = req, cells, bar, log

    def dispatch(self, worker: Any) -> tuple[dict[str, Any], Episode] | None:
        """The (row, episode) `worker` (anything with `running` and `last`, as _Worker) runs next, marked running;
        None: nothing to hand it now."""
        cell = self._next_cell(worker)
        if cell is None:
            return None
        episode = cell.todo.popleft()
        cell.running += 1
        worker.running, worker.last = episode, episode.run_id
        return dict(cell.row), episode

    def waiting(self) -> bool:
        """Whether a cell is left to claim (another rollout holds it): idle workers look again every CLAIM_POLL_S."""
        return any(c.claim is None and not c.closed for c in self.cells.values())

    def release(self) -> None:
        """Every claim still held given back (a stopped or failed rollout)."""
        for cell in self.cells.values():
            if cell.claim is not None:
                cell.claim.release()
                cell.claim = None

    def _next_cell(self, worker: Any) -> _Cell | None:
        held = [c for c in self.cells.values() if c.claim is not None and not c.closed and c.todo]
        last = self.cells.get(worker.last)  # None: no cell yet, or one of an earlier request
        if last is not None and last in held:
            return last
        idle = [c for c in held if not c.running]
        if idle:
            return idle[0]
        for cell in self.cells.values():
            if cell.claim is None and not cell.closed and self._claim(cell):
                return cell
        return min(held, key=lambda c: c.running) if held else None

    def _claim(self, cell: _Cell) -> bool:
        """Take the cell's claim if no other rollout holds it, and drop the episodes the file holds by then; False:
        held elsewhere (said once), or nothing left to run (the claim given back, the cell closed)."""
        run_id = cell.row["run_id"]
        lease = cell_claim(self.req.rollouts, run_id)
        if not lease.try_acquire():
            if not cell.told:
                self.log(f"waiting for run {run_id}, being rolled out by {lease.holder()}")
                cell.told = True
            return False
        cell.claim = lease
        done = set(table.read(self.req.rollouts)["episode_id"].to_list())
        left = deque(e for e in cell.todo if e.id not in done)
        self.bar.update(len(cell.todo) - len(left))  # written by another rollout while it held the claim
        cell.todo = left
        if not left:
            self._close(cell)
            return False
        return True

    def finished(self, worker: Any, outcome: tuple[bool, int, float, bool]) -> None:
        episode, worker.running = worker.running, None
        assert episode is not None
        cell = self.cells[episode.run_id]
        success, steps, seconds, video = outcome
        cell.running -= 1
        cell.done, cell.wins, cell.steps = cell.done + 1, cell.wins + success, cell.steps + steps
        cell.seconds, cell.videos = cell.seconds + seconds, cell.videos + video
        self.bar.set_postfix_str(f"run {episode.run_id}: {cell.wins}/{cell.done} succeeded")
        self.bar.update(1)
        if not cell.todo and not cell.running:
            self.log(summary(self.req.rollouts, cell.row, cell.wins, cell.done, cell.steps, cell.seconds,
                             cell.videos))
            self._close(cell)

    def _close(self, cell: _Cell) -> None:
        if cell.claim is not None:
            cell.claim.release()
            cell.claim = None
        cell.closed = True


def _receive(worker: _Worker) -> tuple[bool, int, float, bool]:
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
    return tuple(body)  # type: ignore[return-value]


def _death(worker: _Worker) -> str:
    worker.process.join(WORKER_GRACE_S)  # its pipe closes a moment before it can be reaped
    code = worker.process.exitcode
    how = f"killed by signal {-code}" if code is not None and code < 0 else f"exit code {code}"
    doing = f"while running {where(worker.running)}" if worker.running is not None else "while idle"
    return (f"rollout worker {worker.index} (pid {worker.process.pid}) died ({how}) {doing}; the episodes written "
            "are kept: rerun the command to run the others")


def _start(n: int, spawn: Callable[[], Simulator], req: RolloutRequest) -> list[_Worker]:
    """n spawned workers, each with its end of a pipe. They start with SIGINT ignored (inherited across exec), so a
    Ctrl-C at the terminal, which reaches the whole process group, stops them through this process only."""
    context = multiprocessing.get_context("spawn")
    team = []
    with _sigint_ignored():
        for i in range(n):
            here, there = context.Pipe()
            process = context.Process(target=serve, args=(there, spawn, req.rollouts, req.command, os.getpid()),
                                      name=f"graftcache-rollout-{i}", daemon=True)
            with _sigterm_held():
                process.start()
            there.close()
            team.append(_Worker(i, process, here))
    return team


@contextmanager
def _sigterm_held() -> Iterator[None]:
    """A SIGTERM held while one worker starts, then delivered: raised between its spawn and the data it is then sent,
    the stop would leave a process that is no team member yet (no stop reaches it) and that dies reading the rest,
    printing an EOFError traceback. (SIGINT is ignored meanwhile, `_sigint_ignored`.) A Python handler holds it, not
    the signal mask, which the process's other threads do not share."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    held: list[int] = []
    previous = signal.signal(signal.SIGTERM, lambda signum, frame: held.append(signum))
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)
        if held:
            signal.raise_signal(signal.SIGTERM)


@contextmanager
def _sigint_ignored() -> Iterator[None]:
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


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


# ---------------------------------------------------------------------------------------------- in the worker
def serve(conn: Connection, spawn: Callable[[], Simulator], rollouts: Path, command: str, parent: int) -> None:
    """A worker's life: build the simulator, then run each (row, episode) sent, write its video and row, and report
    (success, steps, seconds, whether a video was written), until None or the pipe's end. An error is reported as one
    line ("failed"; "broken": building the simulator) and ends the worker; a stop (SIGTERM, its parent's death) ends
    it quietly."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, _terminated)
    try:
        _die_with(parent)
        _thread_locked_bars()
        try:
            sim = spawn()
        except Exception as e:
            conn.send(("broken", one_line(e)))
            return
        try:
            while (job := conn.recv()) is not None:
                row, episode = job
                try:
                    (outcome,) = sim.run(row, [episode])
                    video = record(rollouts, command, episode, outcome)
                except Exception as e:
                    conn.send(("failed", one_line(e)))
                    return
                conn.send(("done", outcome.success, outcome.steps, outcome.seconds, video is not None))
        finally:
            close = getattr(sim, "close", None)
            if close is not None:
                close()
    except (KeyboardInterrupt, EOFError, OSError):  # stopped, or the rollout that started it is gone
        return
    finally:  # a stop while the interpreter exits has nothing left to unwind (it would print from an atexit hook)
        signal.signal(signal.SIGTERM, signal.SIG_DFL)


def _terminated(signum: int, frame: Any) -> None:
    """A stop: raised, and from now on nothing that it cuts short is printed. An object whose `__init__` it
    interrupts can fail in its `__del__` (robosuite's MjRenderContext), which Python would print as "Exception
    ignored in ..." on the terminal before the rollout's one line."""
    sys.unraisablehook = _dropped
    raise Terminated()


def _dropped(unraisable: Any) -> None:
    """sys.unraisablehook of a stopped worker: its debris is not printed (see `_terminated`)."""


def _thread_locked_bars() -> None:
    """tqdm's bars (lerobot's rollout loop opens one, disabled here) share a lock that is by default a
    multiprocessing semaphore, registered with the rollout's resource tracker: a worker killed by SIGKILL (a stop's
    escalation, its parent's death) never unregisters it, and the tracker warns of a "leaked semaphore" on the
    terminal after the rollout's last line. A worker draws no bar of another process: a thread lock serves."""
    from tqdm import tqdm

    tqdm.set_lock(threading.RLock())


def _die_with(parent: int) -> None:
    """SIGKILL to this worker when its parent dies (Linux), so a kill -9 of the rollout leaves no worker running:
    SIGKILL, since SIGTERM is lost where a library swallows what its handler raises (hf-libero's reset loop ends in
    `finally: continue`), and an orphan has no one left to escalate."""
    if sys.platform.startswith("linux"):
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGKILL)
    if os.getppid() != parent:  # died before the prctl
        raise Terminated()

