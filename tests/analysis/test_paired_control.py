"""The paired closed-loop control (issue 43, item 4): the native tower against zero-image on the same episodes,
on a hand-built table whose differences are worked out below.

smolvla / libero_object: native seeds 0 and 1, zero-image rows of siglip and dinov2-s (seed 0 each), a plain siglip
graft (not part of the pairing). Closest approach (m) per episode key k (task 0, episode k, seed 1000 + k, 60 steps,
perturbation 0.03 m; k = 5 is an official-init episode: perturbation_m null in the native row, 0.0 in the
zero-image one, the same scene):

    key   native s0   native s1   native mean   zero siglip   zero dinov2-s   zero mean   d_k
    0     .05         .07         .06           .30           .34             .32         -.26
    1     .10         .06         .08           .28           —               .28         -.20
    2     .04         —           .04           .25           .29             .27         -.23
    5     —           .70         .70           —             .20             .20         +.50
    3     .50         —           (no zero-image episode: unpaired)
    4     —           —           —             .01           (no native episode: unpaired)
    6     .90 with a null env seed: cannot be paired

difference = (-.26 - .20 - .23 + .50) / 4 = -.0475; native = (.06 + .08 + .04 + .70) / 4 = .22, zero-image =
(.32 + .28 + .27 + .20) / 4 = .2675. Native seed 0 against the zero-image mean of its keys: (-.27 - .18 - .23) / 3 < 0
(better); seed 1: (-.25 - .22 + .50) / 3 = +.01 (worse): better on 1 of 2 seeds. Resampled keys reach +.50 means,
so the interval holds 0: not separated. Lift: native .10 on every episode, zero-image 0: d_k = +.10 at every key,
an interval of one point above 0: the native tower is better (higher is better). Success: never, on either side:
d_k = 0, not separated, better on 0 of 2 seeds.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import polars as pl
import pytest
from helpers.tables import row, table

from graftcache import analysis as A
from graftcache.analysis.stats import generator

CELLS = [("smolvla-native", 0, "native"), ("smolvla-native", 1, "native"), ("siglip", 0, "zero-image"),
         ("dinov2-s", 0, "zero-image"), ("siglip", 0, "none")]
NEAR = {  # cell index -> {key: closest approach}
    0: {0: .05, 1: .10, 2: .04, 3: .50, 6: .90}, 1: {0: .07, 1: .06, 5: .70},
    2: {0: .30, 1: .28, 2: .25, 4: .01}, 3: {0: .34, 2: .29, 5: .20}, 4: {0: .15},
}
DIFFS = [-.26, -.20, -.23, .50]  # keys 0, 1, 2, 5: the order of PAIR_KEY, as the bootstrap draws them


def _tables(tmp_path: Path, near: dict = NEAR) -> tuple[pl.DataFrame, Path]:
    rows = [row("smolvla", "libero_object", e, s, 1.0 + i / 10, control=c) for i, (e, s, c) in enumerate(CELLS)]
    # two native cells that ran differently: a table without policy identity (each row its own policy), as a
    # user's table may be; graftcache's rows make every seed's native tower one policy (test_policies.py)
    results = A.analyze(table(rows)).results.with_columns(policy_id=pl.lit(None, dtype=pl.String))
    episodes = []
    for i, keys in near.items():
        native = CELLS[i][2] == "native"
        for k, value in keys.items():
            episodes.append({"run_id": rows[i]["run_id"], "suite": "libero_object", "task_index": 0, "episode": k,
                             "seed": None if k == 6 else 1000 + k, "max_steps": 60,
                             "perturbation_m": (None if native else 0.0) if k == 5 else 0.03, "success": False,
                             "min_target_distance_m": value, "target_lift_m": 0.10 if native else 0.0})
    pl.DataFrame(episodes).write_parquet(tmp_path / "rollouts.parquet")
    return results, tmp_path / "rollouts.parquet"


def _control(tmp_path: Path, near: dict = NEAR) -> dict[str, dict]:
    results, path = _tables(tmp_path, near)
    loop = A.closed_loop(results, A.read_rollouts(path, results))
    return {r["measure"]: r for r in loop.control.iter_rows(named=True)}


def test_the_paired_difference_is_the_hand_computed_one(tmp_path: Path) -> None:
    near = _control(tmp_path)["min_target_distance_m"]
    assert (near["native_cells"], near["zero_image_cells"], near["pairs"]) == (2, 2, 4)
    assert (near["native"], near["zero_image"], near["difference"]) == pytest.approx((.22, .2675, -.0475))
    assert (near["native_seeds_better"], near["native_seeds"]) == (1, 2)
    draws = np.array(DIFFS)[generator(0, "paired-control", "smolvla", "libero_object", "min_target_distance_m")
                            .integers(0, 4, size=(A.N_BOOT, 4))].mean(axis=1)
    assert (near["ci_low"], near["ci_high"]) == pytest.approx(tuple(np.percentile(draws, [2.5, 97.5])))
    assert near["ci_low"] < near["difference"] < 0 < near["ci_high"] <= .50
    assert near["better"] == A.NOT_SEPARATED and near["note"] is None


def test_the_verdict_follows_each_measure_s_direction(tmp_path: Path) -> None:
    got = _control(tmp_path)
    lift = got["target_lift_m"]
    assert (lift["difference"], lift["ci_low"], lift["ci_high"]) == pytest.approx((.10, .10, .10))
    assert lift["better"] == A.NATIVE_BETTER and lift["native_seeds_better"] == 2
    success = got["success"]
    assert (success["difference"], success["better"], success["native_seeds_better"]) == (0, A.NOT_SEPARATED, 0)
    assert got["grasped"]["note"] == ("graded measures unavailable: no native or zero-image episode records "
                                      "grasped")
    far = {i: ({k: v + 1.0 for k, v in keys.items()} if CELLS[i][2] == "native" else keys) for i, keys in NEAR.items()}
    worse = _control(tmp_path, far)["min_target_distance_m"]
    assert worse["better"] == A.ZERO_IMAGE_BETTER and worse["native_seeds_better"] == 0
    assert worse["difference"] == pytest.approx(-.0475 + 1.0)


def test_without_pairs_or_sides_the_control_is_undefined_with_its_reason(tmp_path: Path) -> None:
    apart = {0: {3: .5}, 1: {3: .4}, 2: {4: .3}, 3: {4: .2}, 4: {0: .1}}
    near = _control(tmp_path, apart)["min_target_distance_m"]
    assert (near["pairs"], near["difference"], near["better"]) == (0, None, None)
    assert near["note"] == ("no episode key (suite, task_index, episode, seed, max_steps, perturbation_m) was run "
                            "by both a native and a zero-image cell")
    single = _control(tmp_path, {0: {0: .1}, 2: {0: .3}, 4: {0: .2}})["min_target_distance_m"]
    assert (single["pairs"], single["difference"], single["ci_low"]) == (1, pytest.approx(-.2), None)
    assert single["note"] == "1 paired episode: no interval" and single["native_cells"] == 1
    alone = _control(tmp_path, {0: {0: .1}, 4: {0: .2}})["success"]
    assert alone["note"] == "no zero-image cell with rollouts" and alone["difference"] is None


def test_the_figures_do_not_depend_on_the_order_of_the_rows(tmp_path: Path) -> None:
    results, path = _tables(tmp_path)
    rollouts = A.read_rollouts(path, results)
    first = A.closed_loop(results, rollouts)
    again = A.closed_loop(results, rollouts.sample(fraction=1.0, shuffle=True, seed=5))
    assert first.control.equals(again.control) and first.agreement.equals(again.agreement)
