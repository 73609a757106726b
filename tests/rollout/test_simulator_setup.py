"""The set-up of a process around the LIBERO simulator (graftcache.rollout.simulator_setup): the simulator's set-up
chatter goes to the debug log, in a process that builds real envs (slow)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

os.environ.setdefault("MUJOCO_GL", "egl")  # before MuJoCo is imported (in the test's subprocess): Mesa's EGL


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
    import sys

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
