"""The one loop every rollout's episodes go through (graftcache.rollout.schedule.drive): each claim reads the rollouts
file once (here the loop alone; the whole command's reads: test_chain.py), this process's team of one and a team of
worker processes write the same rows (those the fake simulator's definition gives, by hand: tests/helpers/rollouts.py
paced_rows; Ray's: test_rollout_ray.py), and a cell another
rollout holds is said once and polled until it is given back.

The request is test_rollout_workers.py's: top 1 on libero_object of tests/helpers/tables.py, 6 cells x tasks 0, 3 x
2 episodes, over the fake simulator Paced.
"""

from __future__ import annotations

import threading
import time
from functools import partial
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import polars as pl
import pytest
from helpers.rollouts import VARYING, Paced, paced_request, paced_rows, ran, rolled

from graftcache import results
from graftcache.errors import RolloutError
from graftcache.results.claims import cell_claim, claims_folder
from graftcache.rollout import record, rollouts_file
from graftcache.rollout.episodes import Episode, EpisodeReport, episodes_of
from graftcache.rollout.request import RolloutRequest
from graftcache.rollout.roll_out import roll_out_started
from graftcache.rollout.schedule import Job, Scheduler, drive
from graftcache.rollout.select import select, select_rows
from graftcache.rollout.workers import Workers


def _cells(req: RolloutRequest) -> pl.DataFrame:
    return select_rows(results.read_for_report(req.results), top=1, suites=["libero_object"], log=lambda _: None)


class _Instant:
    """A transport whose one worker finishes each episode at once, writing nothing (so that every read of the
    rollouts file is the scheduler's)."""

    def __init__(self) -> None:
        self.workers = (SimpleNamespace(running=None, last=None),)
        self.sent: list[Episode] = []

    def send(self, worker: Any, job: Job) -> None:
        self.sent.append(job[1])

    def receive(self, timeout: float | None) -> list[tuple[Any, EpisodeReport]]:
        return [(w, EpisodeReport(True, 3, 0.5, None)) for w in self.workers if w.running is not None]

    def stop(self) -> None:
        pass


def test_each_claim_reads_the_rollouts_file_once(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    req = paced_request(tmp_path)
    cells = _cells(req)
    episodes = episodes_of(cells, req, Paced(tmp_path / "traces"))
    written = [e for e in episodes if e.run_id == cells["run_id"][1]][:3]  # another rollout wrote 3 of cell 2's 4
    theirs = paced_rows([cells["run_id"][1]], (0, 3), 2, 7).filter(pl.col("episode_id").is_in([e.id for e in written]))
    assert theirs.height == 3
    record.append(req.rollouts, theirs.with_columns(seconds=pl.lit(0.5), command=pl.lit("")).to_dicts())
    reads: list[Path] = []
    real = rollouts_file.read
    monkeypatch.setattr(rollouts_file, "read", lambda path: reads.append(Path(path)) or real(path))
    transport, lines = _Instant(), []
    scheduler = Scheduler(req.rollouts, {r["run_id"]: r for r in cells.iter_rows(named=True)}, episodes,
                          SimpleNamespace(update=lambda n: None, set_postfix_str=lambda s: None), lines.append)
    drive(scheduler, transport)
    assert reads == [req.rollouts] * cells.height  # one read per claim, one claim per cell
    assert transport.sent == [e for e in episodes if e not in written]
    assert sum(line.startswith("rolled out ") for line in lines) == cells.height
    assert not list(claims_folder(req.rollouts).glob("*.claim"))


def test_one_process_and_two_workers_write_the_rows_the_simulator_defines(tmp_path: Path) -> None:
    alone = rolled(paced_request(tmp_path / "one"), Paced(tmp_path / "one" / "traces"), log=lambda _: None)
    req = paced_request(tmp_path / "two")
    team = Workers(partial(Paced, tmp_path / "two" / "traces"), 2, req)
    two = roll_out_started([select(req)], partial(Paced, tmp_path / "two" / "driver"), team, log=lambda _: None)
    expected = paced_rows(_cells(req)["run_id"].to_list(), (0, 3), 2, 7)
    assert alone.height == two.height == expected.height == 24
    assert alone.drop(VARYING).sort("episode_id").equals(expected)
    assert two.drop(VARYING).sort("episode_id").equals(expected)
    assert len({pid for pid, *_ in ran(tmp_path / "two" / "traces")}) == 2


def test_a_cell_another_rollout_holds_is_said_once_and_run_once_given_back(tmp_path: Path) -> None:
    req = paced_request(tmp_path)
    first = _cells(req)["run_id"][0]
    other = cell_claim(req.rollouts, first)
    assert other.try_acquire()
    threading.Timer(2.5, other.release).start()
    lines: list[str] = []
    start = time.monotonic()
    rows = rolled(req, Paced(tmp_path / "traces"), log=lines.append)
    assert time.monotonic() - start >= 2.5
    waits = [line for line in lines if line.startswith("waiting for ")]
    assert len(waits) == 1 and waits[0].startswith(f"waiting for run {first}, being rolled out by ")
    assert rows.height == 24
    done = [run for _, run, _, _ in ran(tmp_path / "traces")]
    assert len(done) == 24 and done[-4:] == [first] * 4  # the other cells first, then the one given back


@pytest.mark.parametrize("error, line", [
    (RolloutError("run abc: the simulator broke\n  at step 3"), "run abc: the simulator broke"),
    (RolloutError(""), "RolloutError"),
    (ValueError("\n  bad action width 9\nTraceback ..."), "ValueError: bad action width 9"),
    (KeyError(), "KeyError"),
    (OSError(28, "No space left on device"), "OSError: [Errno 28] No space left on device"),
])
def test_an_error_is_said_in_its_first_line_with_its_type_unless_it_is_graftcache_s(error: BaseException,
                                                                                      line: str) -> None:
    """What a failed episode's line quotes (graftcache.errors.first_line, shared by every one-line message that
    quotes a library's error): graftcache's own words as they are, anything else with its type; never a later line,
    never an empty quote."""
    from graftcache.rollout.schedule import one_line

    assert one_line(error) == line
