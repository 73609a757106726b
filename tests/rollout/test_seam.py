"""graftcache.rollout.seam, the one module that reaches past lerobot's, hf-libero's and robosuite's public API.

Its boundary: no other module of graftcache (graftcache/backbones/, whose adapters reach into lerobot's VLAs, is a
house of its own: each backbone declares its reaches, checked against its code and the installed lerobot by
tests/backbones/test_lerobot_reaches.py) reads a private attribute of another library's, imports a private name of
one, or writes an attribute of the simulator's libraries, read statically with `ast` (tests/helpers/reaches.py, the
reader both houses share); the reader is shown each kind of reach it must find. Its version
check: another installed lerobot, hf-libero or robosuite is refused at import, in one line naming both versions and
the pin, through `graftcache rollout` too. Its gate on a simulator's renders, its reuse of rendered frames and its
release of the gripper's command, on stand-ins for lerobot's LiberoEnv and robosuite's MjSim (the real simulator's
episodes: tests/rollout/test_soft_reset.py): blanks until the step the caller keeps, the real render from it on,
the counts the caller checks, the render put back, and a rebuilt simulator refused."""

from __future__ import annotations

import ast
import importlib.util
import sys
from importlib import metadata
from pathlib import Path
from types import ModuleType, SimpleNamespace
from typing import Any

import numpy as np
import pytest
from helpers.probes import run_cli
from helpers.reaches import PACKAGE, own_names, package_trees, private, reaches
from helpers.tables import write_results
from helpers.versions import installed_as, not_installed

import graftcache
import graftcache.rollout
from graftcache.errors import RolloutError
from graftcache.rollout import seam
from graftcache.upstream import WRITTEN_AGAINST, installed

SEAM = PACKAGE / "rollout" / "seam.py"
#: lerobot's VLAs, whose insides the backbone adapters reach into: each reach declared by its backbone and checked
#: against the installed lerobot (tests/backbones/test_lerobot_reaches.py)
BACKBONES = PACKAGE / "backbones"


def _seam_writes(tree: ast.Module, own_fields: set[str]) -> set[str]:
    """The attributes the seam writes on objects that are not its own (its own dataclass's fields aside)."""
    return {n.attr for n in ast.walk(tree) if isinstance(n, ast.Attribute) and isinstance(n.ctx, ast.Store | ast.Del)
            and ast.unparse(n.value) not in ("self", "cls") and n.attr not in own_fields}


def boundary() -> tuple[set[str], set[str], set[str]]:
    """graftcache's own private names, the attributes the seam writes, and the private names the seam reaches."""
    trees = package_trees()
    own = own_names(list(trees.values()))
    written = _seam_writes(trees[SEAM], set(seam.Renders.__dataclass_fields__))
    forbidden = {name for _, name, _ in reaches(trees[SEAM], own, set(), set()) if private(name)}
    return own, written, forbidden


def test_no_module_but_the_seam_reaches_past_the_simulators_api() -> None:
    own, written, forbidden = boundary()
    assert {"_env", "_init_states", "_format_raw_obs", "_get_suite", "_check_grasp"} <= forbidden
    assert {"trange", "init_state_id", "render", "current_action"} <= written
    found = [f"{path.relative_to(PACKAGE.parent)}:{line}: {how}" for path in sorted(PACKAGE.rglob("*.py"))
             if path != SEAM for line, name, how in reaches(ast.parse(path.read_text()), own, written, forbidden)
             if BACKBONES not in path.parents or name in forbidden]
    assert found == [], "reaches past lerobot's, hf-libero's or robosuite's API outside graftcache/rollout/seam.py"


def test_the_boundary_reader_finds_each_kind_of_reach() -> None:
    source = """
from lerobot.envs.libero import _get_suite, TASK_SUITE_MAX_STEPS
from lerobot.scripts import lerobot_eval
import argparse


def f(env, sub: argparse._SubParsersAction):
    self._mine, env._mine = 1, 2
    states = env.unwrapped._init_states
    env.unwrapped.init_state_id = 3
    lerobot_eval.trange = None
    setattr(env, "_env", None)
    env._cache = env.render()
"""
    own, written, forbidden = {"_mine", "_cache"}, {"init_state_id"}, {"_cache"}
    assert reaches(ast.parse(source), own, written, forbidden) == [
        (2, "_get_suite", "from lerobot.envs.libero import _get_suite"),
        (9, "_init_states", "env.unwrapped._init_states"), (10, "init_state_id", "env.unwrapped.init_state_id ="),
        (11, "trange", "lerobot_eval.trange ="), (12, "_env", "setattr(env, '_env', None)"),
        (13, "_cache", "env._cache")]


def _imported_afresh() -> ModuleType:
    """graftcache.rollout.seam executed again in a module of its own (sys.modules untouched), as an import runs it."""
    spec = importlib.util.find_spec("graftcache.rollout.seam")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_another_installed_version_is_refused_at_import_naming_both_and_the_pin(
        monkeypatch: pytest.MonkeyPatch) -> None:
    assert {name: metadata.version(name) for name in seam.LIBRARIES} == WRITTEN_AGAINST  # this venv's
    assert _imported_afresh().LIBRARIES == seam.LIBRARIES  # imports as it is
    installed_as(monkeypatch, lerobot="0.7.0")
    with pytest.raises(RolloutError) as refused:
        _imported_afresh()
    assert str(refused.value) == ("graftcache/rollout/seam.py was written against lerobot 0.6.1, not the installed "
                                  "lerobot 0.7.0: pin lerobot==0.6.1")
    installed_as(monkeypatch, hf_libero="0.2.0", robosuite="1.5.1")
    with pytest.raises(RolloutError) as refused:
        seam.check_versions()
    assert str(refused.value) == ("graftcache/rollout/seam.py was written against lerobot 0.6.1, hf-libero 0.1.4, "
                                  "robosuite 1.4.0, not the installed lerobot 0.7.0, hf-libero 0.2.0, robosuite 1.5.1: "
                                  "pin lerobot==0.6.1 hf-libero==0.1.4 robosuite==1.4.0")


def test_a_library_not_installed_is_left_to_the_simulators_set_up(monkeypatch: pytest.MonkeyPatch) -> None:
    not_installed(monkeypatch, "hf-libero")
    assert installed("hf-libero") is None
    seam.check_versions()


def test_graftcache_rollout_says_it_in_one_line(tmp_path: Path, capsys: pytest.CaptureFixture,
                                                monkeypatch: pytest.MonkeyPatch) -> None:
    """The seam is imported with the simulator (graftcache.rollout.libero), before anything runs: exit 2, one line."""
    for name in ("seam", "libero", "perturb"):
        monkeypatch.delitem(sys.modules, f"graftcache.rollout.{name}", raising=False)
        monkeypatch.delattr(graftcache.rollout, name, raising=False)
    installed_as(monkeypatch, robosuite="1.5.1")
    done = run_cli(["rollout", write_results(tmp_path / "results.parquet")], capsys)
    assert (done.code, done.err.splitlines()) == (2, [
        "graftcache rollout: error: graftcache/rollout/seam.py was written against robosuite 1.4.0, not the installed "
        "robosuite 1.5.1: pin robosuite==1.4.0"])


class Sim:
    """MjSim's render as robosuite's camera sensors call it: a keyword call, an image of the asked size."""

    def __init__(self) -> None:
        self.rendered: list[tuple[str, int]] = []
        self.problem: Any = None

    def render(self, *, camera_name: str, width: int, height: int, depth: bool = False) -> np.ndarray:
        self.rendered.append((camera_name, self.problem.timestep))
        return np.full((height, width, 3), 7, np.uint8)


def _fake_env(settle: int = 3) -> SimpleNamespace:
    sim = Sim()
    gripper = SimpleNamespace(dof=2, current_action=np.array([-0.4, 0.4]))
    problem = SimpleNamespace(sim=sim, timestep=0)
    sim.problem = problem
    hf_env = SimpleNamespace(env=problem, robots=[SimpleNamespace(gripper=gripper)])
    lerobot_env = SimpleNamespace(_env=hf_env, _ensure_env=lambda: None, num_steps_wait=settle,
                                  camera_name=["agentview_image", "robot0_eye_in_hand_image"])
    return SimpleNamespace(unwrapped=lerobot_env, problem=problem, sim=sim, gripper=gripper)


def test_renders_are_blank_before_the_kept_step_and_real_from_it() -> None:
    env = _fake_env()
    with seam.renders_from(env, seam.settle_steps(env)) as renders:
        images = []
        for step in range(5):  # robosuite's step counter: 0 at the reset, then each step's
            env.problem.timestep = step
            images += [env.sim.render(camera_name=c, width=4, height=2) for c in ("agentview", "eye_in_hand")]
    assert [im.shape for im in images] == [(2, 4, 3)] * 10 and all(im.dtype == np.uint8 for im in images)
    assert [int(im.max()) for im in images] == [0] * 6 + [7] * 4
    assert env.sim.rendered == [("agentview", 3), ("eye_in_hand", 3), ("agentview", 4), ("eye_in_hand", 4)]
    assert (renders.done, renders.skipped) == (4, 6) and seam.cameras(env) == 2
    assert "render" not in vars(env.sim)  # the class's render again
    assert int(env.sim.render(camera_name="agentview", width=1, height=1).max()) == 7


def test_none_renders_nothing_and_a_depth_render_is_refused() -> None:
    env = _fake_env()
    with seam.renders_from(env, None) as renders:
        env.problem.timestep = 99
        assert not env.sim.render(camera_name="agentview", width=2, height=2).any()
        with pytest.raises(RolloutError, match="depth or segmentation of agentview.*--reset hard"):
            env.sim.render(camera_name="agentview", width=2, height=2, depth=True)
    assert (renders.done, renders.skipped, env.sim.rendered) == (0, 1, [])


def test_a_simulator_rebuilt_inside_is_refused() -> None:
    env = _fake_env()
    with pytest.raises(RolloutError, match="rebuilt during a soft reset.*--reset hard"):
        with seam.renders_from(env, 3):
            env.problem.sim = Sim()  # what a hard reset does


def test_release_grippers_zeroes_the_held_command() -> None:
    env = _fake_env()
    seam.release_grippers(env)
    assert np.array_equal(env.gripper.current_action, np.zeros(2))


class _Sim:
    """robosuite's MjSim as a camera sensor calls it: render(camera_name=, width=, height=, depth=)."""

    def __init__(self) -> None:
        self.calls: list[str] = []

    def render(self, *, camera_name: str, width: int, height: int, depth: bool = False) -> np.ndarray:
        self.calls.append(camera_name)
        return np.full((height, width, 3), len(self.calls), np.uint8)


def test_frames_reused_renders_each_view_once_inside_and_every_time_after() -> None:
    sim = _Sim()
    with seam.frames_reused(sim):
        first = [sim.render(camera_name=c, width=4, height=2) for c in ("agentview", "wrist", "agentview", "wrist")]
        other_size = sim.render(camera_name="wrist", width=8, height=8)
    assert sim.calls == ["agentview", "wrist", "wrist"]  # each (view, size) once
    assert first[2] is first[0] and first[3] is first[1] and int(first[1][0, 0, 0]) == 2
    assert other_size.shape == (8, 8, 3)
    assert "render" not in vars(sim)  # the class's method again
    after = sim.render(camera_name="agentview", width=4, height=2)
    assert sim.calls[-1] == "agentview" and int(after[0, 0, 0]) == 4
