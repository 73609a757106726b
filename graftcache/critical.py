"""LIBERO's critical intervals, found in the action stream itself: the rule behind CI-MSE.

Critical-interval MSE (CI-MSE, arXiv 2606.29898) restricts the offline action error to the task-critical
segments of an episode, where a wrong action decides success (grasping, releasing), instead of averaging it
over long free-space reaches that any encoder predicts well. LIBERO marks no such segments, so they are
defined here from the data, by one rule with two parameters:

- the gripper is the action dimension `GRIPPER_DIM` (the last one: LIBERO's gripper command, -1 open and
  +1 closed); its state at a step is `action[GRIPPER_DIM] > GRIPPER_THRESHOLD` (0: the sign);
- a *transition* is a step whose gripper state differs from the previous step's in the same episode (the
  first step of an episode is never one);
- a step is *critical* when a transition lies within `WINDOW` steps of it, before or after, in its own
  episode: every transition opens the interval [t - WINDOW, t + WINDOW], clipped to the episode.

Steps are the full-rate action stream (a cache's frame stride thins observations, never actions); LIBERO
records 10 steps a second, so a window of 5 is half a second each side of a grasp or a release. An episode
without a transition has no critical step, and its CI-MSE is null rather than a guess.
"""

from __future__ import annotations

import numpy as np

GRIPPER_DIM = -1
GRIPPER_THRESHOLD = 0.0
WINDOW = 5


def critical_steps(actions: np.ndarray, episode: np.ndarray, *, window: int = WINDOW,
                   gripper_dim: int = GRIPPER_DIM, threshold: float = GRIPPER_THRESHOLD) -> np.ndarray:
    """Bool [M]: which steps of an action stream [M, A] (episodes contiguous, `episode` [M]) are critical."""
    actions, episode = np.asarray(actions), np.asarray(episode)
    closed = actions[:, gripper_dim] > threshold
    transition = np.zeros(len(actions), dtype=bool)
    transition[1:] = (closed[1:] != closed[:-1]) & (episode[1:] == episode[:-1])
    at = np.flatnonzero(transition)
    critical = np.zeros(len(actions), dtype=bool)
    if not len(at):
        return critical
    # the nearest transition of each step, looked for on both sides, must be in the step's own episode
    steps = np.arange(len(actions))
    right = np.searchsorted(at, steps)  # first transition at or after the step
    for side in (np.clip(right - 1, 0, len(at) - 1), np.clip(right, 0, len(at) - 1)):
        near = at[side]
        critical |= (np.abs(near - steps) <= window) & (episode[near] == episode)
    return critical
