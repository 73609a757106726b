"""What lerobot's rollout calls back after the reset and after every step of an episode (its render callback): the
simulator's state read for the graded measures (graftcache.rollout.graded), and, when recording, the frame
lerobot-eval's own callback would keep.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from graftcache.rollout import seam
from graftcache.rollout.graded import State, target_of


def record_frame(frames: list[np.ndarray], env: Any) -> None:
    """lerobot's rollout's render callback: keep the frame lerobot-eval's (eval_policy's render_frame) would keep
    of a one-env vector env."""
    import gymnasium as gym

    frames.append(env.envs[0].render() if isinstance(env, gym.vector.SyncVectorEnv) else env.call("render")[0])


def problem_of(env: Any) -> Any:
    """LIBERO's problem env (the robosuite env built from the task's BDDL) inside lerobot's one-env vector env:
    LiberoEnv -> hf-libero's OffScreenRenderEnv -> its env."""
    return seam.problem(env.envs[0])


def observe(states: list[State], frames: list[np.ndarray] | None, env: Any) -> None:
    """lerobot's rollout's render callback (after the reset and after every step): the simulator's state for the
    graded measures, and the frame when recording."""
    if frames is not None:
        record_frame(frames, env)
    sim = problem_of(env)
    states.append(seam.read_state(sim, target_of(sim)))
