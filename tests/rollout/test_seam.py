"""graftcache.rollout.seam's gate on a simulator's renders and its release of the gripper's command, on a stand-in
for lerobot's LiberoEnv (the real simulator's episodes: tests/rollout/test_soft_reset.py): blanks until the step the
caller keeps, the real render from it on, the counts the caller checks, the render put back, and a rebuilt
simulator refused."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from graftcache.errors import RolloutError
from graftcache.rollout import seam


class Sim:
    """MjSim's render as robosuite's camera sensors call it: a keyword call, an image of the asked size."""

    def __init__(self) -> None:
        self.rendered: list[tuple[str, int]] = []
        self.problem: Any = None

    def render(self, *, camera_name: str, width: int, height: int, depth: bool = False) -> np.ndarray:
        self.rendered.append((camera_name, self.problem.timestep))
        return np.full((height, width, 3), 7, np.uint8)


def _scene(settle: int = 3) -> SimpleNamespace:
    sim = Sim()
    gripper = SimpleNamespace(dof=2, current_action=np.array([-0.4, 0.4]))
    problem = SimpleNamespace(sim=sim, timestep=0)
    sim.problem = problem
    hf_env = SimpleNamespace(env=problem, robots=[SimpleNamespace(gripper=gripper)])
    lerobot_env = SimpleNamespace(_env=hf_env, _ensure_env=lambda: None, num_steps_wait=settle,
                                  camera_name=["agentview_image", "robot0_eye_in_hand_image"])
    return SimpleNamespace(unwrapped=lerobot_env, problem=problem, sim=sim, gripper=gripper)


def test_renders_are_blank_before_the_kept_step_and_real_from_it() -> None:
    scene = _scene()
    with seam.renders_from(scene, seam.settle_steps(scene)) as renders:
        images = []
        for step in range(5):  # robosuite's step counter: 0 at the reset, then each step's
            scene.problem.timestep = step
            images += [scene.sim.render(camera_name=c, width=4, height=2) for c in ("agentview", "eye_in_hand")]
    assert [im.shape for im in images] == [(2, 4, 3)] * 10 and all(im.dtype == np.uint8 for im in images)
    assert [int(im.max()) for im in images] == [0] * 6 + [7] * 4
    assert scene.sim.rendered == [("agentview", 3), ("eye_in_hand", 3), ("agentview", 4), ("eye_in_hand", 4)]
    assert (renders.done, renders.skipped) == (4, 6) and seam.cameras(scene) == 2
    assert "render" not in vars(scene.sim)  # the class's render again
    assert int(scene.sim.render(camera_name="agentview", width=1, height=1).max()) == 7


def test_none_renders_nothing_and_a_depth_render_is_refused() -> None:
    scene = _scene()
    with seam.renders_from(scene, None) as renders:
        scene.problem.timestep = 99
        assert not scene.sim.render(camera_name="agentview", width=2, height=2).any()
        with pytest.raises(RolloutError, match="depth or segmentation of agentview.*--reset hard"):
            scene.sim.render(camera_name="agentview", width=2, height=2, depth=True)
    assert (renders.done, renders.skipped, scene.sim.rendered) == (0, 1, [])


def test_a_simulator_rebuilt_inside_is_refused() -> None:
    scene = _scene()
    with pytest.raises(RolloutError, match="rebuilt during a soft reset.*--reset hard"):
        with seam.renders_from(scene, 3):
            scene.problem.sim = Sim()  # what a hard reset does


def test_release_grippers_zeroes_the_held_command() -> None:
    scene = _scene()
    seam.release_grippers(scene)
    assert np.array_equal(scene.gripper.current_action, np.zeros(2))
