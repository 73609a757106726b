"""Scenes that make the policy look (`graftcache rollout --perturb-cm X`): the task's target slid by a seeded planar
offset before the episode's first step, drawn as the bundled sample draws it (data/render_sample.py's place_target,
written again here: the library does not import data/).

Why: libero_object's official init states place the target identically in all 50, so a policy that ignores its
cameras can still reach it; the sample's demonstrations slide the target up to 3 cm, which is what makes their
actions depend on the images. An episode from init state k: the scene reset to it, the target's free joint moved by
an offset uniform in [-X, X] per planar axis, then SETTLE_STEPS no-op steps (lerobot's LiberoEnv settles its resets
with 10 too); an offset that makes the object collide (it settles more than SETTLE_TOL_M off where it was put, or
turns) is redrawn, and after MAX_DRAWS draws the offset is 0 (the official scene), as the row then records. The draws
come from the episode's seed and task (`rng_of`), so an episode run again, and every cell's episode k, is the same
scene.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np

from graftcache.errors import RolloutError
from graftcache.rollout import seam
from graftcache.rollout.graded import target_of
from graftcache.upstream import WRITTEN_AGAINST

SETTLE_STEPS = 10           # no-op steps after the target is moved (the sample's and lerobot's settling)
SETTLE_TOL_M = 0.005        # the target must settle within 5 mm of where it was put ...
SETTLE_MIN_QUAT_DOT = 0.995  # ... and keep its orientation (|q0 . q| > 0.995: about 10 degrees), else it hit something
MAX_DRAWS = 8               # offsets drawn before falling back to none
#: LIBERO's no-op action: no motion, gripper open (lerobot's get_libero_dummy_action)
NOOP = np.array([0, 0, 0, 0, 0, 0, -1.0])


def rng_of(seed: int, task_index: int) -> np.random.Generator:
    """The draws of the episode seeded `seed` on task `task_index`: every cell's episode k (seeded alike) gets the
    same scene, and tasks of one seed get different ones."""
    return np.random.default_rng([seed, task_index])


def offsets(rng: np.random.Generator, max_m: float) -> Iterator[np.ndarray]:
    """The planar offsets to try, in order: MAX_DRAWS uniform in [-max_m, max_m]^2 (metres)."""
    for _ in range(MAX_DRAWS):
        yield rng.uniform(-max_m, max_m, 2)


def settled(put_xy: np.ndarray, now_xy: np.ndarray, quat_before: np.ndarray, quat_now: np.ndarray) -> bool:
    """Whether an object put at `put_xy` and now at `now_xy` (metres), turned from `quat_before` to `quat_now`, stayed
    where it was put: within SETTLE_TOL_M and the same orientation (either sign of the quaternion)."""
    moved = float(np.linalg.norm(np.asarray(now_xy) - np.asarray(put_xy)))
    return moved < SETTLE_TOL_M and abs(float(np.dot(quat_before, quat_now))) > SETTLE_MIN_QUAT_DOT


def place_target(env: Any, target: str, init_state: np.ndarray, offset: np.ndarray) -> tuple[dict, bool]:
    """Reset hf-libero's env `env` (an OffScreenRenderEnv) to `init_state`, move `target`'s free joint by the
    planar `offset` and let the scene settle: the settled observation, and whether the target stayed put."""
    problem = env.env
    if target not in problem.objects_dict:
        raise RolloutError(f"the task's target {target} is a fixture, not a free object: --perturb-cm moves only "
                           "objects; roll out this task without it")
    joint = problem.objects_dict[target].joints[-1]
    with seam.frames_reused(problem.sim):  # only the last step's images are kept
        obs = env.set_init_state(init_state)
        quat_before = np.array(obs[f"{target}_quat"])
        qpos = problem.sim.data.get_joint_qpos(joint).copy()
        qpos[:2] += offset
        problem.sim.data.set_joint_qpos(joint, qpos)
        problem.sim.forward()
        for _ in range(SETTLE_STEPS - 1):
            env.step(NOOP)
    obs, _, _, _ = env.step(NOOP)
    return obs, settled(qpos[:2], obs[f"{target}_pos"][:2], quat_before, obs[f"{target}_quat"])


def perturb_target(env: Any, target: str, init_state: np.ndarray, max_m: float,
                   rng: np.random.Generator) -> tuple[dict, np.ndarray]:
    """The scene of init state `init_state` with `target` slid by the first offset of `offsets(rng, max_m)` that
    settles, else by none (the official scene, settled alike): its observation and the offset applied."""
    for offset in offsets(rng, max_m):
        obs, ok = place_target(env, target, init_state, offset)
        if ok:
            return obs, offset
    none = np.zeros(2)
    obs, _ = place_target(env, target, init_state, none)
    return obs, none



@dataclass(frozen=True)
class Perturbation:
    """What the next reset of a PerturbedReset perturbs: the target of init state `init_state` slid by up to `max_m`
    per axis, drawn from the episode's `seed` and `task` (rng_of)."""

    init_state: np.ndarray
    max_m: float
    seed: int
    task: int


class PerturbedReset(gym.Wrapper):
    """lerobot's LiberoEnv whose reset (lerobot-eval's: the official init state, settled) is followed, when
    `perturbation` is set, by the target's perturbation. Each reset draws from the episode's seed afresh, so a reset
    done twice gives one scene. It returns the perturbed
    scene's observation (lerobot's formatting of it), so the episode's first step sees the target where it is;
    `offset`: the planar offset the last reset applied, (0, 0) when none. A wrapper, because lerobot's rollout
    resets the env itself and uses the reset's observation for the first step: there is no seam between the two.

    `soft`: the env was built with lerobot's soft reset (graftcache.rollout.seam), whose reset then renders only the
    images that become the observation: its last settling step's, none when a perturbation replaces it."""

    def __init__(self, env: gym.Env, *, soft: bool = False) -> None:
        super().__init__(env)
        self.soft = soft
        self.perturbation: Perturbation | None = None
        self.offset = np.zeros(2)

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[Any, dict]:
        if self.soft:
            obs, info = self._rendering_the_observation_only(seed, options)
        else:
            obs, info = self.env.reset(seed=seed, options=options)
        self.offset = np.zeros(2)
        if (p := self.perturbation) is not None:
            libero = seam.libero_env(self)
            raw, self.offset = perturb_target(libero, target_of(libero.env), p.init_state, p.max_m,
                                              rng_of(p.seed, p.task))
            obs = seam.observation(self, raw)
        return obs, info

    def _rendering_the_observation_only(self, seed: int | None, options: dict | None) -> tuple[Any, dict]:
        """lerobot's reset with the renders nobody sees skipped (seam.renders_from), refused if its observation's
        images were not all rendered."""
        kept = None if self.perturbation is not None else seam.settle_steps(self)
        seam.release_grippers(self)
        with seam.renders_from(self, kept) as renders:
            obs, info = self.env.reset(seed=seed, options=options)
        if kept is not None and renders.done != seam.cameras(self):
            raise RolloutError(f"a soft reset rendered {renders.done} camera image(s) where its observation holds "
                               f"{seam.cameras(self)} (lerobot's reset no longer settles as lerobot "
                               f"{WRITTEN_AGAINST['lerobot']}'s did); roll out with --reset hard")
        return obs, info
