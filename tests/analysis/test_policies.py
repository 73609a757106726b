"""Each policy counted once in the closed-loop analysis, on a hand-built table.

smolvla / libero_object: plain grafts of alpha, beta and gamma at seed 0 (eval_mse 1.0, 1.1, 1.2; closest approach
.10, .14, .12 on each of 4 episode keys), one zero-image policy (policy_id "blind-0", eval_mse 1.35, .40) recorded
and rolled out under all three encoders on the same 4 keys, and a native tower (policy_id "native", eval_mse 0.8,
.05) under seeds 0 and 1, each seed rolled out on the same 4 keys. Distinct policies: 3 grafts, 1 blind, 1 native.

    policy      eval_mse  closest approach
    native      0.80      .05
    alpha       1.00      .10
    beta        1.10      .14
    gamma       1.20      .12
    blind-0     1.35      .40

With controls, over the 5 policies: ranks of -eval_mse (5 4 3 2 1) and of -distance (5 4 2 3 1): rho = 1 - 6 * 2 /
(5 * 24) = 0.9. Counting rows instead (8 cells: the blind policy thrice, the native twice) gives another figure.
"""

from __future__ import annotations

import numpy as np
import polars as pl
import pytest
from helpers.tables import row, table
from scipy import stats

from graftcache import analysis as A
from graftcache.analysis.policies import policies, policy_episodes

CELLS = [("alpha", 0, "none", 1.00, .10, None), ("beta", 0, "none", 1.10, .14, None),
         ("gamma", 0, "none", 1.20, .12, None)]
CELLS += [(e, 0, "zero-image", 1.35, .40, "blind-0") for e in ("alpha", "beta", "gamma")]
CELLS += [("smolvla-native", s, "native", 0.80, .05, "native") for s in (0, 1)]


def _tables(with_policy_id: bool = True) -> tuple[pl.DataFrame, pl.DataFrame]:
    rows = [row("smolvla", "libero_object", e, s, mse, control=c) for e, s, c, mse, _, _ in CELLS]
    results = A.analyze(table(rows)).results
    if with_policy_id:
        results = results.with_columns(policy_id=pl.Series([p for *_, p in CELLS], dtype=pl.String))
    episodes = [{"run_id": r["run_id"], "suite": "libero_object", "task_index": 0, "episode": k, "seed": 1000 + k,
                 "max_steps": 40, "perturbation_m": 0.03 if k else None, "success": False,
                 "min_target_distance_m": near + 0.01 * (k - 1.5)}
                for r, (*_, near, _) in zip(rows, CELLS) for k in range(4)]
    return results, _read(episodes)


def _read(episodes: list[dict]) -> pl.DataFrame:
    """The episodes as read_rollouts returns them: every graded and key column, null where not given."""
    frame = pl.DataFrame(episodes)
    optional = {**A.GRADED_MEASURES, **A.PAIR_KEY}
    return frame.with_columns(*(pl.lit(None, dtype=t).alias(c) for c, t in optional.items()
                                if c not in frame.columns)).select("run_id", "success", *optional)


def test_a_blind_policy_under_three_encoders_is_one_cell() -> None:
    results, rollouts = _tables()
    loop = A.closed_loop(results, rollouts)
    cells = loop.cells
    assert cells.height == 5
    blind = cells.filter(pl.col("control") == "zero-image").row(0, named=True)
    assert (blind["policy_key"], blind["runs"], blind["episodes"]) == ("blind-0", 3, 4)
    assert blind["run_id"] == min(results.filter(pl.col("control") == "zero-image")["run_id"])
    native = cells.filter(pl.col("control") == "native").row(0, named=True)
    assert (native["runs"], native["episodes"]) == (2, 4)
    agree = {r["cells_of"]: r for r in loop.agreement.filter(
        pl.col("score") == "eval_mse", pl.col("measure") == "min_target_distance_m").iter_rows(named=True)}
    assert agree["with controls"]["cells"] == 5 and agree["candidates"]["cells"] == 3
    score, near = np.array([0.8, 1.0, 1.1, 1.2, 1.35]), np.array([.05, .10, .14, .12, .40])
    assert agree["with controls"]["spearman"] == pytest.approx(stats.spearmanr(-score, -near).statistic)
    assert agree["with controls"]["spearman"] == pytest.approx(0.9)
    control = loop.control.filter(pl.col("measure") == "min_target_distance_m").row(0, named=True)
    assert (control["native_cells"], control["zero_image_cells"], control["pairs"]) == (1, 1, 4)
    assert (control["native_seeds"], control["difference"]) == (1, pytest.approx(.05 - .40))


def test_without_policy_id_every_row_is_its_own_policy() -> None:
    results, rollouts = _tables(with_policy_id=False)
    loop = A.closed_loop(results, rollouts)
    assert loop.cells.height == 8 and set(loop.cells["runs"]) == {1}
    assert loop.cells["policy_key"].to_list() == loop.cells["run_id"].to_list()


def test_a_repeated_episode_key_of_one_policy_counts_once_and_keyless_episodes_all_count() -> None:
    """The blind policy's three rows ran keys 0-3 each: 4 episodes, the first run_id's. Episodes with a null env
    seed cannot be recognised as repeats: all kept."""
    results, rollouts = _tables()
    first = min(results.filter(pl.col("control") == "zero-image")["run_id"])
    keyless = rollouts.filter(pl.col("episode") == 0).with_columns(seed=pl.lit(None, dtype=pl.Int64))
    episodes = policy_episodes(results, pl.concat([rollouts, keyless]))
    blind = episodes.filter(pl.col("policy_key") == "blind-0")
    assert blind.height == 4 + 3 and set(blind.drop_nulls("seed")["run_id"]) == {first}
    assert blind.drop_nulls("seed")["perturbation_m"].to_list() == [0.0, 0.03, 0.03, 0.03]
    assert policies(results).height == 5
