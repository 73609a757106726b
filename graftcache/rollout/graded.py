"""Graded progress of an episode, from the simulator's state: how far the policy got where LIBERO's success, one bit,
says nothing (a tiny policy that reaches, grasps and lifts the target but never places it fails exactly as one that
never moves). The measures follow SIMPLER's partial-success measures (Li et al. 2024, "Evaluating Real-World Robot
Manipulation Policies in Simulation", arXiv 2405.05941: grasped, consecutive grasp steps, lifted, moved towards the
goal), read from the state rather than the images, so they are exact.

graftcache.rollout.seam.read_state is the thin reader of the simulator (LIBERO's problem env: a robosuite env built
from the task's BDDL), called after the reset and after every step; here are pure functions over the recorded
`State`s, tested on hand-built sequences. The target is the task's first object of interest (`obj_of_interest[0]`,
parsed from its BDDL: the object to pick first).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

#: consecutive grasping states for `grasped` (SIMPLER's "consecutive grasp" criterion uses 5 steps too)
GRASP_STATES = 5


@dataclass(frozen=True)
class State:
    """What the measures need of one simulator state: the end effector's position (robosuite's grip site,
    `robot0_eef_pos`), the target's position (its root body, `<target>_pos`), both in metres in the world frame;
    whether both gripper fingers touch the target; how many of the task's BDDL goal predicates hold, of how many."""

    eef: tuple[float, float, float]
    target: tuple[float, float, float]
    grasping: bool
    goals_met: int
    goals: int


@dataclass(frozen=True)
class Graded:
    """An episode's graded progress (the rollouts row's columns of the same names):

    - `min_target_distance_m`: the smallest |end effector - target| over every observed state (after the reset and
      after each step): how close the policy came to the object it must pick.
    - `final_target_distance_m`: that distance at the episode's last state.
    - `target_lift_m`: the target's highest height above its height at the first state (the scene settled after
      the reset), clipped at 0 (an object that only sinks or tips is not lifted).
    - `grasped`: the target held between both fingers (a contact of each finger's geoms with the target's) for at
      least GRASP_STATES consecutive states, so a brush of both fingers in passing is no grasp.
    - `goal_fraction`: the share of the task's BDDL goal predicates true at the last state (LIBERO's success is all
      of them).
    """

    target: str
    min_target_distance_m: float
    final_target_distance_m: float
    target_lift_m: float
    grasped: bool
    goal_fraction: float


def distances(states: Sequence[State]) -> np.ndarray:
    """|end effector - target| at each state, metres."""
    eef = np.array([s.eef for s in states], dtype=np.float64)
    target = np.array([s.target for s in states], dtype=np.float64)
    return np.linalg.norm(eef - target, axis=1)


def target_lift(states: Sequence[State]) -> float:
    """The target's highest height above its first state's, clipped at 0."""
    z = np.array([s.target[2] for s in states], dtype=np.float64)
    return float(max(z.max() - z[0], 0.0))


def longest_run(flags: Sequence[bool]) -> int:
    """The longest run of consecutive True in `flags`."""
    best = run = 0
    for flag in flags:
        run = run + 1 if flag else 0
        best = max(best, run)
    return best


def goal_fraction(state: State) -> float:
    """The share of the goal predicates `state` meets."""
    return state.goals_met / state.goals


def measure(target: str, states: Sequence[State]) -> Graded:
    """The graded progress of an episode whose observed states are `states`, in order (at least the one after the
    reset)."""
    if not states:
        raise ValueError("no observed state to measure")
    d = distances(states)
    return Graded(target=target, min_target_distance_m=float(d.min()), final_target_distance_m=float(d[-1]),
                  target_lift_m=target_lift(states),
                  grasped=longest_run([s.grasping for s in states]) >= GRASP_STATES,
                  goal_fraction=goal_fraction(states[-1]))


def target_of(sim: Any) -> str:
    """The task's first object of interest (its BDDL's :obj_of_interest), the object the measures follow."""
    return sim.obj_of_interest[0]
