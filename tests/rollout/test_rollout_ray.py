"""`graftcache rollout --executor ray` (issue 43, item 3; graftcache.executors.ray_rollout): Ray actors, each holding a
simulator, write the rows this process writes for the same episodes, skip what the file holds, and an error inside an
actor is the command's one line naming the run and episode. On a local Ray instance (tests/fixtures/ray_cluster.py,
shared by this module's tests); the fake simulator's tests use test_rollout_workers.py's Paced, which the actors
build by name, and the slow one the session's fitted cells in LIBERO (tests/fixtures/simulator_cells.py)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from functools import partial
from pathlib import Path
from typing import Any

import polars as pl
import pytest
from fixtures.simulator_cells import RolledOut
from helpers.rollouts import VARYING, Paced, paced_request, paced_rows, pids, ran, rolled

from graftcache import results
from graftcache.errors import RolloutError
from graftcache.executors import get_executor
from graftcache.requests import ExecutorSettings
from graftcache.results.claims import claims_folder
from graftcache.rollout import record, rollouts_file
from graftcache.rollout.request import RolloutRequest
from graftcache.rollout.roll_out import roll_out_started
from graftcache.rollout.select import select, select_rows

EPISODES = 24  # test_rollout_workers.py's request: 6 cells x 2 tasks x 2 episodes


def _on_ray(req: RolloutRequest, traces: Path, lines: list[str], actors: int | None = None,
            **paced: Any) -> pl.DataFrame:
    spawn = partial(Paced, traces, **paced)
    team = get_executor(ExecutorSettings(executor="ray")).rollout_team(req, spawn, actors, lines.append)
    return roll_out_started([select(req)], partial(Paced, traces / "driver"), team, log=lines.append)


@pytest.mark.slow
def test_ray_actors_skip_what_the_file_holds_and_write_the_rows_of_this_process(ray_cluster: str,
                                                                                tmp_path: Path) -> None:
    one = rolled(paced_request(tmp_path / "one"), Paced(tmp_path / "one" / "traces"), log=lambda _: None)
    req = paced_request(tmp_path / "ray")
    record.append(req.rollouts, one.head(5).to_dicts())  # a rollout killed after 5 episodes
    lines: list[str] = []
    rows = _on_ray(req, tmp_path / "ray" / "traces", lines, delay=0.05)
    import ray

    actors = int(ray.cluster_resources()["CPU"])  # by default as many as the cluster runs at once, 1 CPU each
    assert f"ray: {actors} simulator actor(s), 0 GPU and 1 CPU each" in lines
    assert f"5 of {EPISODES} episodes already in {req.rollouts}; running the other {EPISODES - 5}" in lines
    assert rows.drop(VARYING).sort("episode_id").equals(one.drop(VARYING).sort("episode_id"))
    cells = select_rows(results.read(req.results), top=1, suites=["libero_object"])["run_id"].to_list()
    assert rows.drop(VARYING).sort("episode_id").equals(paced_rows(cells, (0, 3), 2, 7))  # test_schedule.py's
    episodes = ran(tmp_path / "ray" / "traces")  # run by the actors, each once, none of the 5 written
    assert len(episodes) == len(set(episodes)) == EPISODES - 5
    written = set(one.head(5).select("run_id", "task_index", "episode").rows())
    assert not written & {(run, task, k) for _, run, task, k in episodes}
    assert len(pids(tmp_path / "ray" / "traces")) == actors  # the actors' (the driver's: traces/driver)
    # one line per cell that had episodes to run: the first cell's 4 are among the 5 in the file
    assert sum(line.startswith("rolled out ") for line in lines) == 5
    assert not claims_folder(req.rollouts).exists()


@pytest.mark.slow
def test_an_error_in_a_ray_actor_is_one_line_naming_the_run_and_episode(ray_cluster: str, tmp_path: Path) -> None:
    req = paced_request(tmp_path)
    run = select_rows(results.read(req.results), top=1, suites=["libero_object"])["run_id"][0]
    with pytest.raises(RolloutError) as failed:
        _on_ray(req, tmp_path / "traces", [], actors=1, fail=(run, 3, 1))
    line = str(failed.value)
    assert "\n" not in line
    head, actor = line.rsplit(" (ray actor 0, pid ", 1)
    assert head == f"run {run}, libero_object task 3 episode 1 (seed 8): RuntimeError: the simulator broke"
    assert int(actor.split(" on ")[0]) in pids(tmp_path / "traces")
    assert not claims_folder(req.rollouts).exists()
    rows = rollouts_file.read(req.rollouts)  # whole rows of the episodes before it, that one not among them
    assert 0 < rows.height < EPISODES
    assert (run, 3, 1) not in set(rows.select("run_id", "task_index", "episode").rows())


@pytest.mark.slow  # the session's 4 five-step LIBERO episodes again, by Ray actors
def test_ray_actors_give_the_rows_of_this_process_in_the_simulator(ray_cluster: str, simulator_rollouts: RolledOut,
                                                                  tmp_path: Path,
                                                                  capsys: pytest.CaptureFixture) -> None:
    from helpers.probes import run_cli

    done = run_cli([*simulator_rollouts.argv, "--rollouts", tmp_path / "rollouts.parquet", "--executor", "ray"],
                   capsys)
    assert done.code == 0, done.err[-3000:]
    import ray

    actors = int(ray.cluster_resources()["CPU"])  # as many as the cluster runs at once, 1 CPU each
    assert f"ray: {actors} simulator actor(s), 0 GPU and 1 CPU each" in done.out
    rows = rollouts_file.read(tmp_path / "rollouts.parquet").sort("episode_id")
    assert rows.drop(VARYING).equals(simulator_rollouts.rows.drop(VARYING))
    assert all((tmp_path / video).is_file() for video in rows["video"])


CONSOLE = """
import sys, time
import graftcache.cli.rollout
from graftcache.cli import main
from graftcache.executors.ray_cluster import connect
from graftcache.requests import ExecutorSettings

def run(args):  # the console script's rollout, connected to a Ray instance of its own, until stopped
    connect(ExecutorSettings(executor="ray"), print)
    print("connected", flush=True)
    time.sleep(300)
    return 0

graftcache.cli.rollout.run = run
sys.argv = ["graftcache", "rollout", "results.parquet"]
sys.exit(main())
"""


def test_sigterm_to_a_ray_driver_is_the_commands_one_line(tmp_path: Path) -> None:
    """SIGTERM to `rollout --executor ray` once it started its Ray instance: exit 143 and the command's one line, as
    with the local executor (Ray's C++ handler answered it with a stack dump and an abort, exit 134)."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    with open(tmp_path / "out.txt", "wb") as out, open(tmp_path / "err.txt", "wb") as err:
        driver = subprocess.Popen([sys.executable, "-c", CONSOLE], env=env, stdout=out, stderr=err, cwd=tmp_path)
    try:
        deadline = time.monotonic() + 180
        while "connected" not in (tmp_path / "out.txt").read_text():
            assert driver.poll() is None, (tmp_path / "err.txt").read_text()[-2000:]
            assert time.monotonic() < deadline
            time.sleep(0.1)
        driver.send_signal(signal.SIGTERM)
        code = driver.wait(timeout=60)
    finally:
        if driver.poll() is None:
            driver.kill()
    err = (tmp_path / "err.txt").read_text()
    assert code == 143, err[-2000:]
    assert "SIGTERM received" not in err
    last = err.strip().splitlines()[-1]
    assert last == "graftcache rollout: terminated (SIGTERM); run the same command again to resume"
