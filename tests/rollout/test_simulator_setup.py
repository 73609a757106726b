"""The set-up of a process around the LIBERO simulator (graftcache.rollout.simulator_setup): the simulator's set-up
chatter goes to the debug log, in a process that builds real envs (slow); the stdout filter that does it outlives
its block quietly."""

from __future__ import annotations

import gc
import io
import os
import sys
from pathlib import Path
from typing import Any

import pytest

from graftcache.rollout.simulator_setup import simulator_chatter

os.environ.setdefault("MUJOCO_GL", "egl")  # before MuJoCo is imported (in the test's subprocess): Mesa's EGL


def test_the_chatter_filter_outliving_its_stream_is_collected_quietly(monkeypatch: pytest.MonkeyPatch) -> None:
    """A module imported inside the block that binds sys.stdout then keeps the filter (sympy.strategies.core, which
    torch imports: `from sys import stdout`) until the interpreter's exit, by when the stream it wraps may be closed
    (pytest's capture): the filter is closed with it, and its collection raises nothing. It printed "Exception ignored
    in ... _ChatterFilter ... I/O operation on closed file" at the exit of the slow simulator tests."""
    stream = io.TextIOWrapper(io.BytesIO(), encoding="utf-8")  # as pytest's capture (a StringIO flushes closed)
    monkeypatch.setattr(sys, "stdout", stream)
    with simulator_chatter():
        kept = sys.stdout  # what such a module binds
        print("a line", end="")
    stream.flush()
    assert stream.buffer.getvalue() == b"a line" and not kept.closed
    stream.close()
    assert kept.closed
    unraisable: list[Any] = []
    monkeypatch.setattr(sys, "unraisablehook", unraisable.append)
    del kept
    gc.collect()
    assert unraisable == []


CHATTY = """
import logging, sys
from pathlib import Path
from graftcache.rollout.libero import LiberoSimulator
logging.basicConfig(level=logging.WARNING)  # as lerobot configures it: robosuite's warnings reach the root's handler
if sys.argv[1] == "debug":
    logging.getLogger("graftcache.simulator").setLevel(logging.DEBUG)
sim = LiberoSimulator(Path("results.parquet"), Path("exports"), cache=None, runs=None, max_steps=10)
print("tasks", sim.suite("libero_object").n_tasks)
sim.env("libero_object", 0)
sim.env("libero_object", 1)
print("built")
sim.close()
"""


@pytest.mark.slow  # a process importing the simulator and building two envs: ~40 s on 2 busy cores
def test_the_simulator_s_set_up_chatter_goes_to_the_debug_log(tmp_path: Path) -> None:
    """robosuite's macro-file warning (3 lines, in each process), LIBERO's task-order line (per suite built) and
    lerobot's env-building lines (3 per env) printed 14 lines around these two envs: none reach stdout or stderr, and
    each is in the debug log where it is asked for; the process's own lines pass."""
    import subprocess

    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[2])}
    quiet, debug = (subprocess.run([sys.executable, "-c", CHATTY, mode], capture_output=True, text=True, env=env,
                                   cwd=tmp_path, timeout=600) for mode in ("quiet", "debug"))
    assert quiet.returncode == 0, quiet.stderr[-3000:]
    assert (quiet.stdout, quiet.stderr) == ("tasks 10\nbuilt\n", "")
    assert debug.stdout == "tasks 10\nbuilt\n"
    logged = [line.removeprefix("DEBUG:graftcache.simulator:") for line in debug.stderr.splitlines()]
    assert [line for line in logged if line.startswith(("No private", "[info] using", "Creating", "Built"))] == [
        "No private macro file found!", "[info] using task orders [0, 1, 2, 3, 4, 5, 6, 7, 8, 9]",
        "Creating LIBERO envs | suites=['libero_object'] | n_envs(per task)=1 | init_states=True",
        "[info] using task orders [0, 1, 2, 3, 4, 5, 6, 7, 8, 9]",
        "Built vec env | suite=libero_object | task_id=0 | n_envs=1",
        "Creating LIBERO envs | suites=['libero_object'] | n_envs(per task)=1 | init_states=True",
        "[info] using task orders [0, 1, 2, 3, 4, 5, 6, 7, 8, 9]",
        "Built vec env | suite=libero_object | task_id=1 | n_envs=1"]
