"""`graftcache rollout --workers N` (issue 43, item 3; graftcache.rollout.workers): the rows of one worker, the team's
failures as one line, kill -9 of the rollout or a worker followed by a rerun that runs exactly the missing episodes,
and (slow) the same rows from 1 and 2 workers in the real LIBERO simulator.

The fast tests run the real team (spawned worker processes, pipes, claims, appends) over a fake simulator
(tests/helpers/rollouts.py: Paced), which the workers build by name and which leaves on disk what each ran. The
request is test_rollout.py's: top 1 on libero_object of tests/helpers/tables.py, 6 cells x tasks 0, 3 x 2 episodes.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import os
import signal
import subprocess
import sys
import threading
import time
from collections import Counter
from functools import partial
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import polars as pl
import pytest
from fixtures.simulator_cells import RolledOut
from helpers.rollouts import VARYING, Paced, paced_request, pids, ran, rolled
from helpers.tables import write_results

from graftcache import results
from graftcache.errors import RolloutError
from graftcache.executors.local import LocalExecutor
from graftcache.requests import ExecutorSettings
from graftcache.results.claims import claims_folder
from graftcache.rollout import rollouts_file
from graftcache.rollout.episodes import episodes_of
from graftcache.rollout.request import RolloutRequest
from graftcache.rollout.roll_out import roll_out_started
from graftcache.rollout.schedule import Scheduler, drive
from graftcache.rollout.select import select, select_rows
from graftcache.rollout.workers import Workers

EPISODES = 24  # 6 cells x 2 tasks x 2 episodes


def _first_run(req: RolloutRequest) -> str:
    return select_rows(results.read(req.results), top=1, suites=["libero_object"])["run_id"][0]


def _in_workers(req: RolloutRequest, traces: Path, workers: int = 2, **paced: Any) -> pl.DataFrame:
    team = Workers(partial(Paced, traces, **paced), workers, req)
    return roll_out_started([select(req)], partial(Paced, traces / "driver"), team, log=lambda _: None)


def test_two_workers_write_the_rows_of_one_each_keeping_to_its_cells(tmp_path: Path) -> None:
    (tmp_path / "one").mkdir()
    one = rolled(paced_request(tmp_path / "one"), Paced(tmp_path / "one" / "traces"), log=lambda _: None)
    (tmp_path / "two").mkdir()
    lines: list[str] = []
    req = paced_request(tmp_path / "two")
    team = Workers(partial(Paced, tmp_path / "two" / "traces", delay=0.05), 2, req)
    two = roll_out_started([select(req)], partial(Paced, tmp_path / "two" / "driver"), team, log=lines.append)
    assert one.height == two.height == EPISODES
    assert two.drop(VARYING).sort("episode_id").equals(one.drop(VARYING).sort("episode_id"))
    assert two["seconds"].to_list() == [0.05] * EPISODES  # the workers' outcomes, not the driver's
    episodes = ran(tmp_path / "two" / "traces")
    assert len(episodes) == EPISODES and len({p for p, *_ in episodes}) == 2  # both workers ran episodes, none twice
    assert len(set(episodes)) == EPISODES
    # a worker takes a cell no other serves while there is one: only the last cell may be shared
    runners = Counter(run for run, _ in {(run, pid) for pid, run, *_ in episodes})
    assert sum(n > 1 for n in runners.values()) <= 1 and len(runners) == 6
    assert lines[1] == "2 worker processes, each with a simulator of its own"
    assert sum(line.startswith("rolled out ") for line in lines) == 6  # one line per cell, as one worker says
    assert not claims_folder(req.rollouts).exists() and not multiprocessing.active_children()


def test_one_team_serves_requests_in_turn_starting_once(tmp_path: Path) -> None:
    """The closed-loop demo's use (graftcache.demo_closed_loop): requests of other cells and other episodes per task,
    one team. A worker's last cell belongs to the request before (a KeyError in the scheduler once); the third request
    repeats cells of the first and runs only what it left missing. Rows as one process's; two worker processes in
    all."""
    path = tmp_path / "results.parquet"
    write_results(path)
    cells = select_rows(results.read(path), top=1, suites=["libero_object"])["run_id"].to_list()
    assert len(cells) == 6

    def requests(folder: Path) -> list[RolloutRequest]:
        folder.mkdir()
        over = ({"run_ids": tuple(cells[:3]), "episodes_per_task": 1}, {"run_ids": tuple(cells[3:])},
                {"run_ids": tuple(cells[:3])})
        return [paced_request(folder, results=path, **o) for o in over]

    alone = requests(tmp_path / "one")
    one = pl.concat([rolled(r, Paced(tmp_path / "one" / "traces"), log=lambda _: None) for r in alone])
    reqs = requests(tmp_path / "two")
    lines: list[str] = []
    team = Workers(partial(Paced, tmp_path / "two" / "traces", delay=0.02), 2, reqs[0])
    two = roll_out_started([select(r) for r in reqs], partial(Paced, tmp_path / "two" / "driver"), team,
                           log=lines.append)
    assert two.height == EPISODES  # the first request's 6 episodes are the third's first 6: counted once
    assert two.drop(VARYING).sort("episode_id").equals(one.unique("episode_id").drop(VARYING).sort("episode_id"))
    assert len(pids(tmp_path / "two" / "traces")) == 2  # started once, for the three requests
    episodes = ran(tmp_path / "two" / "traces")
    assert len(episodes) == len(set(episodes)) == EPISODES
    assert Counter(run for _, run, *_ in episodes) == {run: 4 for run in cells}
    assert f"6 of 12 episodes already in {reqs[2].rollouts}; running the other 6" in lines
    assert not claims_folder(reqs[2].rollouts).exists() and not multiprocessing.active_children()


def test_requests_of_one_team_must_share_the_rollouts_file(tmp_path: Path) -> None:
    first, second = paced_request(tmp_path), paced_request(tmp_path, rollouts=tmp_path / "other.parquet")
    with pytest.raises(RolloutError, match="requests rolled out by one team must share their rollouts file"):
        roll_out_started([select(first), select(second)], partial(Paced, tmp_path / "driver"), None,
                         log=lambda _: None)


def test_an_error_in_a_worker_is_one_line_naming_the_run_and_episode(tmp_path: Path) -> None:
    req = paced_request(tmp_path)
    run = _first_run(req)
    with pytest.raises(RolloutError) as failed:
        _in_workers(req, tmp_path / "traces", fail=(run, 3, 1))
    line = str(failed.value)
    assert "\n" not in line
    head, worker = line.rsplit(" (rollout worker ", 1)
    assert head == f"run {run}, libero_object task 3 episode 1 (seed 8): RuntimeError: the simulator broke"
    pid = int(worker.split(", pid ")[1].rstrip(")"))
    assert pid in pids(tmp_path / "traces") and pid != os.getpid()
    assert not multiprocessing.active_children()  # the other worker was stopped
    assert not claims_folder(req.rollouts).exists()
    # whole rows of episodes the workers finished (the stopped one may have finished one it had no time to write)
    rows = rollouts_file.read(req.rollouts)
    finished = {(run_id, task, k) for _, run_id, task, k in ran(tmp_path / "traces")}
    assert 0 < rows.height < EPISODES and set(rows.select("run_id", "task_index", "episode").rows()) <= finished
    assert (run, 3, 1) not in finished


def test_a_worker_killed_mid_episode_is_one_line_and_a_rerun_runs_exactly_the_rest(tmp_path: Path) -> None:
    req = paced_request(tmp_path)
    run = _first_run(req)
    with pytest.raises(RolloutError) as failed:
        _in_workers(req, tmp_path / "killed", die=(run, 3, 0))
    assert str(failed.value).split(" (pid ")[0] in ("rollout worker 0", "rollout worker 1")
    assert str(failed.value).split(") ", 1)[1] == (
        f"died (killed by signal 9) while running run {run}, libero_object task 3 episode 0 (seed 7); the episodes "
        "written are kept: rerun the command to run the others")
    written = rollouts_file.read(req.rollouts)
    assert 0 < written.height < EPISODES
    rows = _in_workers(req, tmp_path / "rerun")
    assert len(ran(tmp_path / "rerun")) == EPISODES - written.height
    assert rows.height == EPISODES and rows["episode_id"].n_unique() == EPISODES
    assert not multiprocessing.active_children()


ROLLOUT = """
import sys
from functools import partial
from pathlib import Path
from helpers.rollouts import Paced
from graftcache.rollout.request import RolloutRequest
from graftcache.rollout.roll_out import roll_out_started
from graftcache.rollout.select import select
from graftcache.rollout.workers import Workers
here = Path(sys.argv[1])
req = RolloutRequest(results=here / "results.parquet", rollouts=here / "rollouts.parquet", top=1,
                     suites=("libero_object",), tasks=(0, 3), episodes_per_task=2, seed=7, command="killed")
roll_out_started([select(req)], partial(Paced, here / "driver"),
                 Workers(partial(Paced, here / "traces", delay=0.4), 2, req))
"""


def _gone(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    return False


def test_kill_9_of_a_two_worker_rollout_leaves_whole_rows_no_worker_and_a_rerun_runs_the_rest(tmp_path: Path) -> None:
    req = paced_request(tmp_path)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    rollout = subprocess.Popen([sys.executable, "-c", ROLLOUT, str(tmp_path)], env=env, stdout=subprocess.DEVNULL,
                               stderr=subprocess.PIPE)
    deadline = time.monotonic() + 120
    while rollouts_file.read(req.rollouts).height < 3:  # a few episodes in, both workers busy
        assert rollout.poll() is None, rollout.stderr.read().decode()[-2000:]
        assert time.monotonic() < deadline
        time.sleep(0.05)
    os.kill(rollout.pid, signal.SIGKILL)
    rollout.wait()
    workers = pids(tmp_path / "traces")
    assert len(workers) == 2
    deadline = time.monotonic() + 10
    while not all(_gone(p) for p in workers):  # the kernel's SIGTERM to each (PR_SET_PDEATHSIG)
        assert time.monotonic() < deadline, "a worker outlived its rollout"
        time.sleep(0.05)
    written = rollouts_file.read(req.rollouts)  # whole rows only, each episode once
    assert 3 <= written.height < EPISODES and written["episode_id"].n_unique() == written.height
    rows = _in_workers(req, tmp_path / "rerun")
    assert len(ran(tmp_path / "rerun")) == EPISODES - written.height
    assert rows.height == EPISODES and rows["episode_id"].n_unique() == EPISODES
    assert not claims_folder(req.rollouts).exists()


def _frames(path: Path) -> Any:
    """An mp4's decoded frames, (n, H, W, 3) uint8."""
    import av
    import numpy as np

    with av.open(str(path)) as container:
        return np.stack([f.to_ndarray(format="rgb24") for f in container.decode(video=0)])


@pytest.mark.slow  # 4 five-step episodes by 2 workers, of the session's fitted cells (by 1: the session's rollout)
def test_two_workers_give_the_rows_and_frames_of_one_in_the_simulator(simulator_rollouts: RolledOut, tmp_path: Path,
                                                                      capsys: pytest.CaptureFixture) -> None:
    """2 cells x 2 episodes of 5 steps in LIBERO, rolled out by this process (the session's `simulator_rollouts`) and
    by `--workers 2` into another file: the same rows (seconds and command aside) and, since 5 failed steps say
    little, the same decoded frames of every episode: the simulator's states after the reset and each step, which
    differ between the episodes (init states 0 and 1)."""
    import numpy as np
    from helpers.probes import run_cli

    done = run_cli([*simulator_rollouts.argv, "--rollouts", tmp_path / "rollouts.parquet", "--workers", 2], capsys)
    assert done.code == 0, done.err[-3000:]
    one, two = simulator_rollouts.rows, rollouts_file.read(tmp_path / "rollouts.parquet").sort("episode_id")
    assert one.height == 4 and sorted(one["episode"].to_list()) == [0, 0, 1, 1]
    assert two.drop(VARYING).equals(one.drop(VARYING))
    assert (one["steps"] == 5).all() and not multiprocessing.active_children()
    videos = {(r["run_id"], r["episode"]): r["video"] for r in one.iter_rows(named=True)}
    for video in videos.values():
        seen = _frames(simulator_rollouts.folder / video)
        assert seen.shape == (6, 256, 256, 3) and np.array_equal(_frames(tmp_path / video), seen)
    run = one["run_id"][0]
    first, second = (_frames(simulator_rollouts.folder / videos[run, k]) for k in (0, 1))
    assert not np.array_equal(first, second)


def test_a_team_whose_episodes_another_rollout_wrote_meanwhile_ends(tmp_path: Path) -> None:
    """A second rollout sharing the file asks for its episodes while the first still runs: every episode it found
    missing is written by the time it holds the cells' claims. Its team closes both cells without running one and
    returns (it waited forever for a worker's report once)."""
    req = paced_request(tmp_path)
    first = rolled(req, Paced(tmp_path / "first"), log=lambda _: None)
    rows = {r["run_id"]: r for r in select_rows(results.read(req.results), top=1, suites=["libero_object"])
            .iter_rows(named=True)}
    stale = episodes_of(pl.DataFrame(list(rows.values())), req, Paced(tmp_path / "driver"))
    assert len(stale) == EPISODES and first.height == EPISODES
    team = Workers(partial(Paced, tmp_path / "second"), 2, req)
    bar = SimpleNamespace(update=lambda n: counted.append(n), set_postfix_str=lambda _: None)
    counted: list[int] = []
    def run() -> None:  # the second rollout's loop, as graftcache.rollout.roll_out.roll_out drives it
        team.begin(req, len(stale), lambda _: None)
        drive(Scheduler(req.rollouts, rows, stale, bar, lambda _: None), team)

    runner = threading.Thread(target=run, daemon=True)
    try:
        runner.start()
        runner.join(10)
        assert not runner.is_alive(), "the team waited for a report no worker owed it"
    finally:
        team.close()
    assert sum(counted) == EPISODES and ran(tmp_path / "second") == []
    assert rollouts_file.read(req.rollouts).height == EPISODES and not multiprocessing.active_children()


CONSOLE = """
import sys
from functools import partial
from pathlib import Path
import graftcache.cli.rollout
from graftcache.cli import main
from helpers.rollouts import Paced
from graftcache.rollout.request import RolloutRequest
from graftcache.rollout.roll_out import roll_out_started
from graftcache.rollout.select import select
from graftcache.rollout.workers import Workers
here, spin, built = Path(sys.argv[1]), sys.argv[2], sys.argv[3:]

def run(args):  # the console script's rollout, over Paced simulators, one of whose episodes spins in the reset loop
    req = RolloutRequest(results=here / "results.parquet", rollouts=here / "rollouts.parquet", top=1,
                         suites=("libero_object",), tasks=(0, 3), episodes_per_task=2, seed=7, command="stopped")
    debris = (built[0], 0, 0) if built else None  # the other worker's first episode: stopped mid-build
    team = Workers(partial(Paced, here / "traces", delay=0.2, spin=(spin, 0, 0), debris=debris), 2, req)
    roll_out_started([select(req)], partial(Paced, here / "driver"), team)
    return 0

graftcache.cli.rollout.run = run
sys.argv = ["graftcache", "rollout", str(here / "results.parquet")]
sys.exit(main())
"""


def _spinning_console(tmp_path: Path, debris: bool = False) -> tuple[subprocess.Popen, list[int]]:
    """`graftcache rollout --workers 2` as the console script runs it, in a session of its own (a terminal's process
    group), once one worker spins in hf-libero's reset loop (and, with `debris`, the other is building a HalfBuilt);
    and the pids of its two workers."""
    req = paced_request(tmp_path)
    cells = select_rows(results.read(req.results), top=1, suites=["libero_object"])["run_id"].to_list()
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    with open(tmp_path / "stderr.txt", "wb") as err:  # a file: a worker that outlives the console keeps it open
        console = subprocess.Popen([sys.executable, "-c", CONSOLE, str(tmp_path), *cells[: 1 + debris]], env=env,
                                   stdout=subprocess.DEVNULL, stderr=err, start_new_session=True)
    deadline = time.monotonic() + 120
    markers = ("spinning-*", "building-*") if debris else ("spinning-*",)
    while not all(list((tmp_path / "traces").glob(m)) for m in markers) or len(pids(tmp_path / "traces")) < 2:
        assert console.poll() is None, (tmp_path / "stderr.txt").read_text()[-2000:]
        assert time.monotonic() < deadline
        time.sleep(0.05)
    return console, pids(tmp_path / "traces")


def _all_gone(workers: list[int], within: float) -> bool:
    deadline = time.monotonic() + within
    while not all(_gone(p) for p in workers):
        if time.monotonic() > deadline:
            for pid in workers:  # the test's own clean-up: nothing it started outlives it
                with contextlib.suppress(ProcessLookupError):
                    os.kill(pid, signal.SIGKILL)
            return False
        time.sleep(0.05)
    return True


def test_ctrl_c_stops_a_worker_spinning_in_the_reset_loop(tmp_path: Path) -> None:
    """Ctrl-C (SIGINT to the terminal's process group) while a worker spins in hf-libero's reset loop, which swallows
    the SIGTERM of the stop: the stop goes on to SIGKILL after its grace period, and the command ends in its one line
    (it printed the line, then hung until a second Ctrl-C)."""
    console, workers = _spinning_console(tmp_path)
    os.killpg(console.pid, signal.SIGINT)
    try:
        console.wait(timeout=30)
    except subprocess.TimeoutExpired:
        os.killpg(console.pid, signal.SIGKILL)
        console.wait()
        _all_gone(workers, 0)
        pytest.fail("the stopped rollout did not exit")
    lines = (tmp_path / "stderr.txt").read_text().strip().splitlines()
    assert console.returncode == 130, lines[-20:]
    assert lines[-1] == "graftcache rollout: interrupted; run the same command again to resume", lines[-20:]
    assert _all_gone(workers, 5)


def test_kill_9_of_the_rollout_ends_a_worker_spinning_in_the_reset_loop(tmp_path: Path) -> None:
    """A worker dies with its rollout even where it swallows SIGTERM (hf-libero's reset loop): the kernel's signal
    on the parent's death is SIGKILL."""
    console, workers = _spinning_console(tmp_path)
    os.kill(console.pid, signal.SIGKILL)
    console.wait()
    assert _all_gone(workers, 10), "a worker outlived its rollout"


def test_a_team_asked_for_more_workers_than_cpus_starts_one_per_cpu_and_says_so(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """--workers 5 on a process that may run on 2 CPUs: 2 simulators start, said in one line, and they write the rows
    (--workers 1000 started up to 1000 before the episodes were known)."""
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 1})
    req = paced_request(tmp_path)
    lines: list[str] = []
    team = LocalExecutor(ExecutorSettings()).rollout_team(req, partial(Paced, tmp_path / "traces"), 5, lines.append)
    rows = roll_out_started([select(req)], partial(Paced, tmp_path / "driver"), team, log=lines.append)
    assert lines[0] == "--workers 5: starting 2, one per CPU this process may run on"
    assert len(pids(tmp_path / "traces")) == 2 and rows.height == EPISODES
    assert not multiprocessing.active_children()


def test_a_stopped_team_prints_nothing_after_its_workers(tmp_path: Path) -> None:
    """SIGTERM to the console while one worker spins in hf-libero's reset loop (so it ends by SIGKILL) and the other
    is stopped mid-build of an object whose `__del__` then fails (robosuite's MjRenderContext): exit 143, and stderr
    holds none of the workers' debris, neither "Exception ignored ... __del__" nor the resource tracker's
    "leaked semaphore" warning (the killed worker's tqdm lock), before or after the command's one line."""
    console, workers = _spinning_console(tmp_path, debris=True)
    console.send_signal(signal.SIGTERM)
    try:
        console.wait(timeout=30)
    finally:
        if console.poll() is None:
            os.killpg(console.pid, signal.SIGKILL)
    deadline = time.monotonic() + 15
    with contextlib.suppress(ProcessLookupError):  # the resource tracker speaks once the last of the session is gone
        while time.monotonic() < deadline:
            os.killpg(console.pid, 0)
            time.sleep(0.1)
    err = (tmp_path / "stderr.txt").read_text()
    assert console.returncode == 143, err[-3000:]
    assert "Exception ignored" not in err and "leaked" not in err and "Traceback" not in err, err[-3000:]
    assert err.strip().splitlines()[-1] == ("graftcache rollout: terminated (SIGTERM); run the same command again "
                                            "to resume")
    assert _all_gone(workers, 5)


STARTING = """
import os, signal, sys
from functools import partial
from pathlib import Path
from multiprocessing import util
import graftcache.cli.rollout
from graftcache.cli import main
from helpers.rollouts import Paced
from graftcache.rollout.request import RolloutRequest
from graftcache.rollout.workers import Workers
here, spawned = Path(sys.argv[1]), []
spawn = util.spawnv_passfds

def spawn_then_stop(*args):  # SIGTERM as the second worker's process exists, before it was sent what to run
    spawned.append(spawn(*args))
    if len(spawned) == 2:
        os.kill(os.getpid(), signal.SIGTERM)
    return spawned[-1]

def run(args):
    req = RolloutRequest(results=here / "results.parquet", rollouts=here / "rollouts.parquet", command="stopped")
    util.spawnv_passfds = spawn_then_stop
    Workers(partial(Paced, here / "traces"), 3, req)
    return 0

graftcache.cli.rollout.run = run
sys.argv = ["graftcache", "rollout", str(here / "results.parquet")]
sys.exit(main())
"""


def test_a_stop_while_the_team_starts_leaves_no_worker_and_no_traceback(tmp_path: Path) -> None:
    """SIGTERM while the team's workers are being spawned, just after one's process exists: it is held until that
    worker has what to run, then stops the command in its one line (exit 143) and every worker with it, quietly
    (the half-started one printed an EOFError traceback, reading what it was never sent)."""
    write_results(tmp_path / "results.parquet")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    with open(tmp_path / "stderr.txt", "wb") as err:
        console = subprocess.Popen([sys.executable, "-c", STARTING, str(tmp_path)], env=env,
                                   stdout=subprocess.DEVNULL, stderr=err, start_new_session=True)
    try:
        console.wait(timeout=60)
        deadline = time.monotonic() + 20
        with contextlib.suppress(ProcessLookupError):  # every process of its session gone: workers, resource tracker
            while True:
                os.killpg(console.pid, 0)
                assert time.monotonic() < deadline, "a worker outlived its stopped rollout"
                time.sleep(0.1)
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(console.pid, signal.SIGKILL)
    err = (tmp_path / "stderr.txt").read_text()
    assert console.returncode == 143, err[-3000:]
    assert err.strip().splitlines() == ["graftcache rollout: terminated (SIGTERM); run the same command again to "
                                        "resume"]
