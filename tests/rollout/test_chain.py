"""`graftcache rollout` followed from its command line to the rows it writes, as a newcomer would follow it: one chain
of modules, none visited twice on any call stack (module A calling B which calls back into A is a stop the reader
must climb back to), the results file read once and the rollouts file once per claim, besides the reads that the
request's own bookkeeping owes (graftcache.rollout.roll_out: the command's check of the file before anything starts,
the request's written episodes, the rows it returns) and each append's read under the file's lease.

The command runs in this process over the fake simulator Scripted (tests/helpers/rollouts.py), with sys.setprofile
recording, at each call of a graftcache function, the graftcache modules on the call stack. One kind of frame is
left out, and only it: a rule of a request's setting (a lambda of graftcache.requests, such as the executor's
choices) that graftcache.settings evaluates as it checks the request. Rules are data written as code, declared
beside their fields and evaluated by the one checker of every request; the command's ExecutorSettings is checked
that way before anything of the rollout runs.
"""

from __future__ import annotations

import sys
from pathlib import Path
from types import FrameType
from typing import Any

import polars as pl
import pytest
from helpers.probes import Outcome, run_cli
from helpers.rollouts import Scripted
from helpers.tables import write_results

from graftcache.results import reading, writing
from graftcache.rollout import libero, select

FLAGS = ("--top", "1", "--suites", "libero_object", "--tasks", "0,3", "--episodes-per-task", "2", "--seed", "7")
#: graftcache.rollout.select of helpers.tables' results: the top cell of each (backbone, encoder) on libero_object
CELLS = 6


class Trace:
    """A profile function: each call stack on which a graftcache module is visited twice (its frames not one run),
    each read of a Parquet file (graftcache.results.reading.load_table) with the graftcache functions on the stack at
    that moment, and how many times the rows were selected."""

    def __init__(self) -> None:
        self.revisits: set[tuple[str, ...]] = set()
        self.reads: list[tuple[Path, tuple[str, ...]]] = []
        self.selections = 0  # calls of graftcache.rollout.select.select_rows

    def __call__(self, frame: FrameType, event: str, arg: Any) -> None:
        if event != "call" or not str(frame.f_globals.get("__name__", "")).startswith("graftcache"):
            return
        stack, f = [], frame
        while f is not None:
            module = str(f.f_globals.get("__name__", ""))
            if module.startswith("graftcache") and not _rule(f):
                stack.append((module, f.f_code.co_name))
            f = f.f_back
        stack.reverse()
        runs = [m for i, (m, _) in enumerate(stack) if i == 0 or stack[i - 1][0] != m]
        if len(runs) != len(set(runs)):
            self.revisits.add(tuple(f"{m}.{name}" for m, name in stack))
        if frame.f_code is select.select_rows.__code__:
            self.selections += 1
        if frame.f_code is reading.load_table.__code__:
            self.reads.append((Path(frame.f_locals["path"]), tuple(name for _, name in stack)))


def _rule(frame: FrameType) -> bool:
    """Whether `frame` runs a request setting's rule for graftcache.settings (see the module docstring)."""
    caller = frame.f_back
    return (frame.f_globals.get("__name__") == "graftcache.requests" and frame.f_code.co_name == "<lambda>"
            and caller is not None and caller.f_globals.get("__name__") == "graftcache.settings")


def _traced(folder: Path, flags: list[str], capsys: pytest.CaptureFixture) -> tuple[Outcome, Trace]:
    """`graftcache rollout RESULTS FLAGS` run under a Trace, into an empty rollouts file beside the results (an absent
    one is read as no rows without opening it, so every read of it is counted), after a run of the same flags into
    another file: every import done and every lazy one taken, so that no module's body counts as a call."""
    results_path = folder / "results.parquet"
    warm = run_cli(["rollout", results_path, *flags, "--rollouts", folder / "warm" / "rollouts.parquet"], capsys)
    assert warm.code == 0, warm.err
    pl.read_parquet(folder / "warm" / "rollouts.parquet").clear().write_parquet(folder / "rollouts.parquet")
    trace = Trace()
    sys.setprofile(trace)
    try:
        done = run_cli(["rollout", results_path, *flags], capsys)
    finally:
        sys.setprofile(None)
    assert done.code == 0, done.err
    assert not trace.revisits, "\n".join(" -> ".join(stack) for stack in sorted(trace.revisits))
    assert [path for path, _ in trace.reads if path == results_path] == [results_path]
    assert trace.selections == 1
    return done, trace


def test_a_rollout_is_one_chain_of_modules_reading_each_file_as_often_as_it_must(
        tmp_path: Path, capsys: pytest.CaptureFixture, monkeypatch: pytest.MonkeyPatch) -> None:
    results_path = write_results(tmp_path / "results.parquet")
    rollouts = tmp_path / "rollouts.parquet"
    monkeypatch.setattr(libero, "LiberoSimulator", lambda *args, **kwargs: Scripted())
    _, trace = _traced(tmp_path, list(FLAGS), capsys)
    assert {path for path, _ in trace.reads} == {results_path, rollouts}
    rollout_reads = [functions for path, functions in trace.reads if path == rollouts]
    appends = [f for f in rollout_reads if writing.append_table.__name__ in f]
    claims = [f for f in rollout_reads if "_claim" in f and f not in appends]
    owed = [f for f in rollout_reads if f not in appends and f not in claims]
    assert len(appends) == CELLS * 2 * 2  # one per episode written: 6 cells x 2 tasks x 2 episodes
    assert len(claims) == CELLS  # once per claim, one claim per cell
    assert len(owed) == 3, owed  # the command's check, the request's written episodes, the rows it returns
    assert pl.read_parquet(rollouts).height == CELLS * 2 * 2


def test_a_sequential_rollout_visits_no_module_twice_and_selects_once(
        tmp_path: Path, capsys: pytest.CaptureFixture, monkeypatch: pytest.MonkeyPatch) -> None:
    """`--until-resolved`: the looks (graftcache.rollout.sequential.looks) narrow the command's selection, look after
    look, in the same chain."""
    write_results(tmp_path / "results.parquet")
    monkeypatch.setattr(libero, "LiberoSimulator", lambda *args, **kwargs: Scripted())
    done, _ = _traced(tmp_path, [*FLAGS, "--top", "2", "--until-resolved", "6"], capsys)
    assert "look 1:" in done.out  # a second look ran
