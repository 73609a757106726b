"""CI-MSE: the critical-interval rule (graftcache/critical.py) and the score (graftcache/scoring.py) against
a tiny stream worked out by hand."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from graftcache.critical import WINDOW, critical_steps
from graftcache.fit.data import LowDim
from graftcache.scoring import score_chunks

# Two episodes, one stream. Gripper (last dim): episode 0 closes at step 3 and opens at step 9; episode 1
# (steps 10-13) stays closed, and its first step differs from episode 0's last without being a transition.
GRIPPER = np.array([-1, -1, -1, 1, 1, 1, 1, 1, 1, -1, 1, 1, 1, 1], dtype=np.float32)
EPISODE = np.array([0] * 10 + [1] * 4)
ACTIONS = np.stack([np.linspace(0, 1, 14, dtype=np.float32), GRIPPER], axis=1)


@pytest.mark.parametrize(("window", "critical"), [
    (0, [3, 9]),
    (1, [2, 3, 4, 8, 9]),  # 10 is within 1 of step 9 but in episode 1
    (2, [1, 2, 3, 4, 5, 7, 8, 9]),
])
def test_critical_steps_are_windows_around_gripper_transitions(window, critical):
    got = critical_steps(ACTIONS, EPISODE, window=window)
    assert np.flatnonzero(got).tolist() == critical


def test_default_window_and_no_transition():
    assert WINDOW == 5
    assert np.flatnonzero(critical_steps(ACTIONS, EPISODE)).tolist() == list(range(10))
    assert not critical_steps(ACTIONS[10:], EPISODE[10:]).any()  # episode 1 alone: nothing is critical


def _low(window: int) -> LowDim:
    """Frames at stream steps 0 and 6 (episode 0) and 11 (episode 1), chunks of 4."""
    start = np.array([0, 6, 11])
    return LowDim(rows=np.arange(3), index=start, episode_index=np.array([0, 0, 1]), frame_index=np.array([0, 6, 1]),
                  state=torch.zeros(3, 1), task_index=torch.zeros(3, dtype=torch.int64), stream_start=start,
                  stream_end=np.array([10, 10, 14]), actions=torch.from_numpy(ACTIONS), chunk=4, tasks=("t",),
                  critical=critical_steps(ACTIONS, EPISODE, window=window))


def test_ci_mse_by_hand():
    low = _low(window=1)
    pos = np.arange(3)
    _, pad = low.action_chunks(pos)
    critical = low.critical_chunks(pos)
    # steps 0-3, 6-9 and 11, 12, 13, 13 (padded): critical are 2, 3 and 8, 9
    assert critical.tolist() == [[False, False, True, True], [False, False, True, True], [False] * 4]
    assert pad[2].tolist() == [False, False, False, True]
    target = torch.zeros(3, 4, 2)
    pred = torch.tensor([
        [[1, 1], [2, 2], [3, 3], [4, 4]],      # squared error per step 1, 4, 9, 16
        [[0, 0], [1, 1], [0, 2], [2, 0]],      # 0, 1, 2, 2
        [[5, 5], [5, 5], [5, 5], [9, 9]],      # 25, 25, 25 (and a padded 81)
    ], dtype=torch.float32)
    score = score_chunks(pred, target, pred, target, pad, low.episode_index[pos], critical=critical)
    assert score.ci_mse == pytest.approx((9 + 16 + 2 + 2) / 4)
    assert score.ci_per_episode == {0: pytest.approx(29 / 4), 1: None}
    # the full-chunk score is unchanged: per frame 7.5, 1.25, 25 (padded step left out)
    assert score.mse == pytest.approx((7.5 + 1.25 + 25) / 3)
    assert score.per_episode == {0: pytest.approx((7.5 + 1.25) / 2), 1: pytest.approx(25.0)}


def test_ci_mse_is_none_without_a_critical_step():
    low = _low(window=1)
    pos = np.array([2])
    actions, pad = low.action_chunks(pos)
    pred = torch.ones(1, 4, 2)
    score = score_chunks(pred, actions * 0, pred, actions * 0, pad, low.episode_index[pos],
                         critical=low.critical_chunks(pos))
    assert score.ci_mse is None and score.ci_per_episode == {1: None} and score.mse == pytest.approx(1.0)


def test_scores_do_not_depend_on_the_thread_count():
    """A held-out set past torch's parallel grain (2000 frames x 50 steps x 7 dims, more critical pairs than one
    thread sums alone): every score is the same bits on one intra-op thread and on two, and the mean numpy takes
    in float64 of the squared errors it selects."""
    g = torch.Generator().manual_seed(0)
    n, chunk, dims = 2000, 50, 7
    pred, target = torch.randn(n, chunk, dims, generator=g), torch.randn(n, chunk, dims, generator=g)
    pad = torch.zeros(n, chunk, dtype=torch.bool)
    pad[:, 45:] = True
    critical = torch.rand(n, chunk, generator=g) < 0.5
    episodes = np.repeat(np.arange(4), n // 4)
    scores, threads = {}, torch.get_num_threads()
    try:
        for t in (1, 2):
            torch.set_num_threads(t)
            scores[t] = score_chunks(pred, target, pred, target, pad, episodes, critical=critical)
    finally:
        torch.set_num_threads(threads)
    assert scores[1] == scores[2]
    squared = ((pred - target) ** 2).double().numpy()
    keep = (critical & ~pad).numpy()
    assert scores[1].ci_mse == pytest.approx(squared.mean(-1)[keep].mean(), rel=1e-6)
    assert scores[1].mse == pytest.approx(squared[:, :45].mean(), rel=1e-6)
