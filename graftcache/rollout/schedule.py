"""The one loop every rollout's episodes go through (`drive`), whoever runs them: this process (the team of one,
graftcache.rollout.teams.InProcess), worker processes (graftcache.rollout.workers.Workers) or Ray actors
(graftcache.executors.ray_rollout.Actors). The team is the loop's transport: it sends a worker an episode and gives
back the reports of the episodes finished; the `Scheduler` decides which episode a free worker runs next and holds
the claims and tallies of the cells. So claims, the reread of the rollouts file, the bar and each cell's summary line
are kept once, and a team only says how an episode reaches a simulator and how its report comes back.

Scheduling: a worker that finishes gets the next episode of the cell it ran last (its policy stays loaded), else the
episodes of a cell no worker is serving (one already claimed, else one it claims now), and only then joins another
worker's cell. A cell is claimed without waiting (graftcache.results.claims.cell_claim): one another rollout holds
is said once ("waiting for ...") and tried again every CLAIM_POLL_S, and once taken, the rollouts file is read again
(once) to drop what the other rollout wrote meanwhile. So two rollouts sharing a file, of any team, never run one
episode twice.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

from graftcache.errors import GraftcacheError, first_line
from graftcache.file_lease import FileLease
from graftcache.results.claims import cell_claim
from graftcache.rollout import rollouts_file
from graftcache.rollout.episodes import Episode, EpisodeReport

#: how often cells that other rollouts hold are tried again while nothing else is left to hand out
CLAIM_POLL_S = 1.0
VIDEOS_FOLDER = "videos"  # beside the rollouts file: videos/RUN_ID/<episode>.mp4 (graftcache.rollout.record.video_of)

#: what a worker is sent: the cell's results row and the episode to run
Job = tuple[dict[str, Any], Episode]


class Worker(Protocol):
    """A team's worker as the scheduler sees it: the episode it runs (None: free) and the run_id of the cell it ran
    last, whose policy it holds."""

    running: Episode | None
    last: str | None


class Transport(Protocol):
    """How a team's workers get episodes and give back reports (see the module docstring)."""

    workers: Sequence[Worker]

    def send(self, worker: Worker, job: Job) -> None:
        """Start `job` on `worker` (this process's team of one runs it at once)."""

    def receive(self, timeout: float | None) -> list[tuple[Worker, EpisodeReport]]:
        """The episodes finished since the last call, each with its worker, waiting up to `timeout` seconds (None:
        until one finishes) when none has; a worker's failure or death is raised as one line naming its episode."""

    def stop(self) -> None:
        """The loop was stopped or failed: end what the workers run, before their cells' claims are given back."""


def one_line(e: BaseException) -> str:
    """An error as one line: a GraftcacheError's own words, anything else with its type."""
    if isinstance(e, GraftcacheError) or not str(e).strip():
        return first_line(e)
    return f"{type(e).__name__}: {first_line(e)}"


def describe(row: Mapping[str, Any]) -> str:
    return f"{row['backbone']}/{row['encoder']}/{row['suite']} seed {row['seed']} control {row['control']}"


def summary(rollouts: Path, row: Mapping[str, Any], wins: int, episodes: int, steps: int, seconds: float,
            videos: int) -> str:
    """The line a cell's rolled-out episodes end with."""
    kept = f"; {videos} video(s) in {rollouts.parent / VIDEOS_FOLDER / row['run_id']}" if videos else ""
    return (f"rolled out {describe(row)} (run {row['run_id']}): {wins}/{episodes} succeeded, {episodes} episode(s) in "
            f"{seconds:.0f} s ({seconds / max(steps, 1):.2f} s a step){kept}")


@dataclass
class _Cell:
    """A cell's episodes as the scheduler hands them out, and what its finished ones gave (its summary line)."""

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


def cells_of(rows: Mapping[str, Mapping[str, Any]], missing: Sequence[Episode]) -> dict[str, _Cell]:
    """The missing episodes by cell, in the order of their first episode."""
    return {run_id: _Cell(rows[run_id], deque(e for e in missing if e.run_id == run_id))
            for run_id in dict.fromkeys(e.run_id for e in missing)}


class Scheduler:
    """Which episode a free worker runs next (see the module docstring), and the bookkeeping of finished ones: the
    cells' claims, the bar (one per episode written or found written) and each cell's summary line."""

    def __init__(self, rollouts: Path, rows: Mapping[str, Mapping[str, Any]], missing: Sequence[Episode], bar: Any,
                 log: Callable[[str], None]) -> None:
        self.rollouts, self.cells, self.bar, self.log = rollouts, cells_of(rows, missing), bar, log

    def done(self) -> bool:
        return all(c.closed for c in self.cells.values())

    def dispatch(self, worker: Worker) -> Job | None:
        """The (row, episode) `worker` runs next, marked running; None: nothing to hand it now."""
        cell = self._next_cell(worker)
        if cell is None:
            return None
        episode = cell.todo.popleft()
        cell.running += 1
        worker.running, worker.last = episode, episode.run_id
        return dict(cell.row), episode

    def waiting(self) -> bool:
        """Whether a cell is left to claim (another rollout holds it): free workers look again every CLAIM_POLL_S."""
        return any(c.claim is None and not c.closed for c in self.cells.values())

    def release(self) -> None:
        """Every claim still held given back (a stopped or failed rollout)."""
        for cell in self.cells.values():
            if cell.claim is not None:
                cell.claim.release()
                cell.claim = None

    def finished(self, worker: Worker, report: EpisodeReport) -> None:
        episode, worker.running = worker.running, None
        assert episode is not None
        cell = self.cells[episode.run_id]
        cell.running -= 1
        cell.done, cell.wins, cell.steps = cell.done + 1, cell.wins + report.success, cell.steps + report.steps
        cell.seconds, cell.videos = cell.seconds + report.seconds, cell.videos + (report.video is not None)
        self.bar.set_postfix_str(f"run {episode.run_id}: {cell.wins}/{cell.done} succeeded")
        self.bar.update(1)
        if not cell.todo and not cell.running:
            self.log(summary(self.rollouts, cell.row, cell.wins, cell.done, cell.steps, cell.seconds, cell.videos))
            self._close(cell)

    def _next_cell(self, worker: Worker) -> _Cell | None:
        held = [c for c in self.cells.values() if c.claim is not None and not c.closed and c.todo]
        last = self.cells.get(worker.last) if worker.last is not None else None  # None: of an earlier request
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
        lease = cell_claim(self.rollouts, run_id)
        if not lease.try_acquire():
            if not cell.told:
                self.log(f"waiting for run {run_id}, being rolled out by {lease.holder()}")
                cell.told = True
            return False
        cell.claim = lease
        done = set(rollouts_file.read(self.rollouts)["episode_id"].to_list())
        left = deque(e for e in cell.todo if e.id not in done)
        self.bar.update(len(cell.todo) - len(left))  # written by another rollout while it held the claim
        cell.todo = left
        if not left:
            self._close(cell)
            return False
        return True

    def _close(self, cell: _Cell) -> None:
        if cell.claim is not None:
            cell.claim.release()
            cell.claim = None
        cell.closed = True


def drive(scheduler: Scheduler, transport: Transport) -> None:
    """Run the scheduler's episodes on the transport's workers until every cell is closed: each free worker handed
    its next episode, each report tallied as it comes back. Members wait for a report without a timeout only while
    one is running and no cell is left to claim; else they look again every CLAIM_POLL_S. Every claim is given back
    however it ends; a stop or a worker's failure stops the transport first (also when a stop is raised again
    meanwhile: graftcache.cli.signals._Stop)."""
    try:
        while not scheduler.done():
            for worker in transport.workers:
                if worker.running is None and (job := scheduler.dispatch(worker)) is not None:
                    transport.send(worker, job)
            if scheduler.done():  # another rollout wrote what was left: no report is owed
                break
            running = any(m.running is not None for m in transport.workers)
            timeout = None if running and not scheduler.waiting() else CLAIM_POLL_S
            for worker, report in transport.receive(timeout):
                scheduler.finished(worker, report)
    except BaseException:
        transport.stop()
        raise
    finally:
        scheduler.release()

