"""Graded progress (graftcache.rollout.graded) and the target's perturbation draws (graftcache.rollout.perturb), as
pure functions over hand-built state sequences whose answers are worked out by hand here; the simulator's side is
in test_graded_sim.py."""

from __future__ import annotations

import math

import numpy as np
import pytest

from graftcache.rollout.graded import GRASP_STATES, State, longest_run, measure, target_lift
from graftcache.rollout.perturb import MAX_DRAWS, offsets, rng_of, settled


def _state(eef: tuple[float, float, float], target: tuple[float, float, float], grasping: bool = False,
           goals_met: int = 0, goals: int = 1) -> State:
    return State(eef=eef, target=target, grasping=grasping, goals_met=goals_met, goals=goals)


def test_reach_grasp_lift_sequence_gives_its_known_measures() -> None:
    """The end effector starts 0.5 m from the target (0.3 m in x, 0.4 m in z), comes within 0.02 m, holds it for 5
    states while lifting it 0.1 m, then lets it fall to 0.04 m above where it started and ends 0.05 m aside and
    0.1 m above it; 1 of 2 goal predicates holds at the end."""
    target0 = (0.1, -0.2, 0.05)
    states = [_state((0.4, -0.2, 0.45), target0, goals=2),
              _state((0.1, -0.2, 0.07), target0, goals=2)]
    for lift in (0.0, 0.02, 0.05, 0.08, 0.1):  # 5 grasping states, the target carried 2 cm below the grip
        states.append(_state((0.1, -0.2, 0.07 + lift), (0.1, -0.2, 0.05 + lift), grasping=True, goals=2))
    states.append(_state((0.1, -0.15, 0.09 + 0.1), (0.1, -0.2, 0.09), goals_met=1, goals=2))
    graded = measure("cup_1", states)
    assert graded.target == "cup_1"
    assert graded.min_target_distance_m == pytest.approx(0.02)
    # last state: eef - target = (0, 0.05, 0.1)
    assert graded.final_target_distance_m == pytest.approx(math.hypot(0.05, 0.1))
    assert graded.target_lift_m == pytest.approx(0.1)
    assert graded.grasped is True
    assert graded.goal_fraction == 0.5


def test_a_grasp_needs_five_consecutive_states() -> None:
    assert GRASP_STATES == 5
    assert longest_run([]) == 0
    assert longest_run([True, True, False, True, True, True, False]) == 3
    assert longest_run([False, True, True, True, True, True]) == 5
    far, near = (0.0, 0.0, 0.3), (0.0, 0.0, 0.0)
    touching_twice = [_state(far, near, g) for g in (True, True, True, False, True, True, True, True)]  # 3, then 4
    assert measure("x", touching_twice).grasped is False
    held = [_state(far, near, g) for g in (False, True, True, True, True, True, False)]
    assert measure("x", held).grasped is True


def test_lift_is_above_the_first_state_and_never_negative() -> None:
    sinking = [_state((0, 0, 1), (0, 0, z)) for z in (0.05, 0.049, 0.03)]  # knocked over: lower, never lifted
    assert target_lift(sinking) == 0.0
    raised_then_dropped = [_state((0, 0, 1), (0, 0, z)) for z in (0.05, 0.04, 0.071, 0.02)]
    assert target_lift(raised_then_dropped) == pytest.approx(0.021)


def test_a_single_state_episode_and_no_state() -> None:
    """An episode that ends at once (its first step succeeded) still has the state after its reset and after its
    step; one state alone measures as itself."""
    (alone,) = [_state((0.0, 0.3, 0.4), (0.0, 0.0, 0.0), goals_met=3, goals=3)]
    graded = measure("bowl", [alone])
    assert (graded.min_target_distance_m, graded.final_target_distance_m) == (pytest.approx(0.5), pytest.approx(0.5))
    assert (graded.target_lift_m, graded.grasped, graded.goal_fraction) == (0.0, False, 1.0)
    with pytest.raises(ValueError, match="^no observed state to measure$"):
        measure("bowl", [])


def test_offsets_are_seeded_uniform_in_the_square_and_paired_across_cells() -> None:
    """Every cell's episode k (same seed, same task) gets the same draws; another task or seed others; each draw
    lies in [-max, max] per axis and is numpy's uniform of the Generator seeded [seed, task]."""
    first = list(offsets(rng_of(1000, 0), 0.03))
    assert len(first) == MAX_DRAWS == 8
    assert np.array_equal(np.stack(first), np.stack(list(offsets(rng_of(1000, 0), 0.03))))
    expected = np.random.default_rng([1000, 0]).uniform(-0.03, 0.03, (MAX_DRAWS, 2))
    assert np.array_equal(np.stack(first), expected)
    assert np.abs(np.stack(first)).max() <= 0.03 and np.abs(np.stack(first)).max() > 0.01
    assert not np.array_equal(first[0], next(offsets(rng_of(1000, 1), 0.03)))
    assert not np.array_equal(first[0], next(offsets(rng_of(1001, 0), 0.03)))


def test_settled_means_within_5_mm_and_the_same_orientation() -> None:
    q = np.array([0.0, 0.0, 0.0, 1.0])
    assert settled(np.array([0.1, 0.2]), np.array([0.1, 0.2 + 0.0049]), q, q)
    assert not settled(np.array([0.1, 0.2]), np.array([0.1 + 0.004, 0.2 + 0.004]), q, q)  # 5.7 mm off
    assert settled(np.array([0.0, 0.0]), np.array([0.0, 0.0]), q, -q)  # the same rotation, the other sign
    half = np.radians(12) / 2  # turned 12 degrees about z: |q0 . q| = cos(6 deg) = 0.9945 < 0.995
    assert not settled(np.array([0.0, 0.0]), np.array([0.0, 0.0]), q, np.array([0, 0, np.sin(half), np.cos(half)]))
    half = np.radians(8) / 2  # 8 degrees: cos(4 deg) = 0.9976
    assert settled(np.array([0.0, 0.0]), np.array([0.0, 0.0]), q, np.array([0, 0, np.sin(half), np.cos(half)]))


