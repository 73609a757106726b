"""`graftcache rollout --reset soft` (the default: lerobot's soft reset, the gripper's command released, the renders
nobody sees skipped; graftcache.rollout.seam) gives the episodes `--reset hard` (lerobot-eval's own reset) gives, in
the real LIBERO simulator: the same rows and the same frames, bit for bit. The tolerance is zero, and it has to be:
a policy's actions follow its images, so a difference at the reset could grow over an episode. Without the gripper's
command released (lerobot's soft reset alone), the fingers start each episode but the first a little off and the
wrist camera sees it: the test fails."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fixtures.simulator_cells import RolledOut
from helpers.rollouts import VARYING

from graftcache.rollout import rollouts_file


def _frames(path: Path) -> Any:
    """An mp4's decoded frames, (n, H, W, 3) uint8."""
    import av

    with av.open(str(path)) as container:
        return np.stack([f.to_ndarray(format="rgb24") for f in container.decode(video=0)])


@pytest.mark.slow  # 4 five-step episodes with hard resets, of the session's fitted cells (soft: the session's rollout)
def test_soft_and_hard_resets_give_the_same_rows_and_frames(simulator_rollouts: RolledOut, tmp_path: Path,
                                                           capsys: pytest.CaptureFixture) -> None:
    """2 cells x 2 episodes of 5 steps on libero_object task 0, one env serving all four in turn: each soft reset
    follows an episode whose policy moved the arm and gripper. The session's rollout ran them with the default
    (soft) reset; here with hard resets: success, steps, graded measures and every frame (after the reset and each
    step) are equal exactly."""
    from helpers.probes import run_cli

    assert "--reset" not in simulator_rollouts.argv  # the session's rollout ran the default
    done = run_cli([*simulator_rollouts.argv, "--rollouts", tmp_path / "rollouts.parquet", "--reset", "hard"], capsys)
    assert done.code == 0, done.err[-3000:]
    soft, hard = simulator_rollouts.rows, rollouts_file.read(tmp_path / "rollouts.parquet").sort("episode_id")
    assert soft.height == 4 and soft["min_target_distance_m"].null_count() == 0
    assert hard.drop(VARYING).equals(soft.drop(VARYING))
    for video in soft["video"]:
        seen = _frames(simulator_rollouts.folder / video)
        assert seen.shape == (6, 256, 256, 3) and np.array_equal(_frames(tmp_path / video), seen)
