"""Where graftcache's episode reset reaches past the public API of lerobot's LIBERO env and of hf-libero's, in one
place: what the fast reset (`graftcache rollout --reset soft`) needs of their insides, each reach named here, and the
versions they were read in (WRITTEN_AGAINST). A newer lerobot may move any of them; a soft reset that rebuilt the
simulator, or whose observation was not rendered (graftcache.rollout.perturb.PerturbedReset checks `Renders`), is
refused rather than feeding the policy a blank image.

The fast reset is two things. lerobot's own soft reset (its LIBERO config's `hard_reset=False`: robosuite's
`sim.reset()` instead of a new MjSim and render context each episode; the init state is set over it either way).
And renders skipped: lerobot's reset renders both cameras on robosuite's reset, on setting the init state and on each
of its settling no-op steps, and only the last step's images become the observation. The physics never reads an
image, so skipping the others leaves every state as it was; `renders_from` gates the MjSim's render by robosuite's
step counter, which a soft reset keeps counting on the same MjSim (a hard reset builds a new one, whose renders it
cannot reach: there the gate is not installed).
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import numpy as np

from graftcache.errors import RolloutError

#: the versions whose insides this module was read in
WRITTEN_AGAINST = {"lerobot": "0.6.1", "hf-libero": "0.1.4", "robosuite": "1.4.0"}


def libero_env(scene: Any) -> Any:
    """hf-libero's OffScreenRenderEnv inside lerobot's LiberoEnv `scene` (any gym wrapper of it), built on first
    use as lerobot's reset builds it (LiberoEnv._ensure_env, LiberoEnv._env)."""
    lerobot_env = scene.unwrapped
    lerobot_env._ensure_env()
    return lerobot_env._env


def settle_steps(scene: Any) -> int:
    """The no-op steps lerobot's reset settles the scene with (LiberoEnv.num_steps_wait)."""
    return int(scene.unwrapped.num_steps_wait)


@dataclass
class Renders:
    """What `renders_from` let through: `done`, the camera images rendered; `skipped`, those answered blank."""

    done: int = 0
    skipped: int = 0


@contextmanager
def renders_from(scene: Any, step: int | None) -> Iterator[Renders]:
    """Inside, the camera renders of `scene`'s MjSim (robosuite's env.sim.render, which its camera sensors call)
    are answered with a blank image while robosuite's step counter (env.timestep: 0 after a reset, the settling or
    policy step in progress after) is below `step` (None: all of them), and rendered from it on. Blank images
    must never reach a policy: the caller checks `Renders.done` against the images it keeps. The MjSim must outlive
    the block (a soft reset: a hard one replaces it, and the gate with it)."""
    problem = libero_env(scene).env
    sim, counts = problem.sim, Renders()
    render, own = sim.render, "render" in vars(sim)

    def gated(*args: Any, camera_name: str, width: int, height: int, depth: bool = False, **kwargs: Any) -> Any:
        if step is not None and problem.timestep >= step:
            counts.done += 1
            return render(*args, camera_name=camera_name, width=width, height=height, depth=depth, **kwargs)
        if depth or args or kwargs:
            raise RolloutError(f"robosuite asked for a render graftcache cannot skip (depth or segmentation of "
                               f"{camera_name}); roll out with --reset hard")
        counts.skipped += 1
        return np.zeros((height, width, 3), np.uint8)

    sim.render = gated
    try:
        yield counts
    finally:
        rebuilt = problem.sim is not sim
        if own:
            sim.render = render
        else:
            del sim.render
    if rebuilt:
        raise RolloutError("the simulator was rebuilt during a soft reset (the env reset hard: lerobot "
                           f"{WRITTEN_AGAINST['lerobot']}'s hard_reset=False no longer holds); roll out with "
                           "--reset hard")


def release_grippers(scene: Any) -> None:
    """Forget the gripper command each robot's gripper holds (robosuite's gripper.current_action, which its grippers
    integrate each step), as a hard reset's newly built grippers start: robosuite 1.4.0's soft reset keeps the last
    episode's, so the settling steps would open the gripper from where the last episode left it."""
    for robot in libero_env(scene).robots:
        robot.gripper.current_action = np.zeros(robot.gripper.dof)


def cameras(scene: Any) -> int:
    """The camera images an observation of `scene` holds (lerobot's LiberoEnv.camera_name)."""
    return len(scene.unwrapped.camera_name)
