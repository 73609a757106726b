"""Pairwise encoder verdicts: each pair of candidate encoders' offline and closed-loop paired differences, checked
against scipy.stats (ttest_rel, t.interval) on a hand-built table.

smolvla / libero_object, plain cells of four encoders at fit seeds 0-3, eval_mse (EVAL_MSE) chosen so that offline
alpha beats beta, delta beats alpha, beta and gamma, and alpha vs gamma is not resolved. Closed loop: 4 episode keys
per fit seed; each episode's closest approach is the scene's difficulty (shared by every encoder, it cancels in a
pair) plus the encoder's effect (EFFECT: gamma best, then alpha = delta, then beta) plus a small fixed noise. So:

    pair            offline   closed   verdict
    alpha, beta     a         a        agree
    alpha, delta    b         -        offline only   (equal effects)
    alpha, gamma    -         b        closed loop only
    beta, gamma     b         b        agree
    beta, delta     b         b        agree
    delta, gamma    a         b        disagree       (delta better offline, gamma in closed loop)

-> 3 of 4 pairs resolved by both agree. Around them: a zero-image policy rolled out under three encoders (one
policy_id) and a native cell, which are not candidates; an episode with a null env seed (unpairable); an episode
only alpha ran; and beta's seed-3 rows rolled out twice under two run_ids of one policy_id (each key once).
"""

from __future__ import annotations

import itertools

import numpy as np
import polars as pl
import pytest
from helpers.tables import row, table
from scipy import stats

from graftcache.analysis.pairwise import pairwise, pairwise_summary
from graftcache.errors import GraftcacheError

EVAL_MSE = {"alpha": [1.00, 1.02, 0.98, 1.01], "beta": [1.10, 1.13, 1.07, 1.12],
            "gamma": [1.00, 1.05, 0.95, 1.03], "delta": [0.90, 0.93, 0.87, 0.92]}
EFFECT = {"alpha": 0.10, "beta": 0.15, "gamma": 0.05, "delta": 0.10}
SCENE = [0.05, 0.20, 0.10, 0.30]  # difficulty of episode key k
NOISE = {e: np.random.default_rng(i).normal(0, 0.01, size=(4, 4)) for i, e in enumerate(EFFECT)}
EXPECTED = {("alpha", "beta"): "agree", ("alpha", "delta"): "offline only", ("alpha", "gamma"): "closed loop only",
            ("beta", "gamma"): "agree", ("beta", "delta"): "agree", ("delta", "gamma"): "disagree"}


def _near(encoder: str, seed: int, k: int) -> float:
    return SCENE[k] + EFFECT[encoder] + NOISE[encoder][seed, k]


def _episode(run_id: str, k: int, value: float, env_seed: int | None = None) -> dict:
    return {"run_id": run_id, "suite": "libero_object", "task_index": 0, "episode": k,
            "seed": 1000 + k if env_seed is None else env_seed, "max_steps": 40, "perturbation_m": 0.03,
            "success": False, "min_target_distance_m": value, "target_lift_m": 1.0 - value}


def _tables() -> tuple[pl.DataFrame, pl.DataFrame]:
    rows = [row("smolvla", "libero_object", e, s, mse) for e, values in EVAL_MSE.items()
            for s, mse in enumerate(values)]
    rows += [row("smolvla", "libero_object", e, 0, 1.35, control="zero-image") for e in ("alpha", "beta", "gamma")]
    rows.append(row("smolvla", "libero_object", "smolvla-native", 0, 0.8, control="native"))
    policy = [r["run_id"] for r in rows[:16]] + ["blind-0"] * 3 + [rows[19]["run_id"]]
    results = table(rows).with_columns(policy_id=pl.Series(policy))
    beta_3 = results.filter(pl.col("run_id") == rows[7]["run_id"])  # rows are encoder-major: beta seed 3
    results = pl.concat([results, beta_3.with_columns(run_id=pl.lit("~beta-seed-3-again"))])
    episodes = [_episode(r["run_id"], k, _near(r["encoder"], r["seed"], k)) for r in rows[:16] for k in range(4)]
    episodes += [_episode("~beta-seed-3-again", k, 9.0) for k in range(4)]  # repeats: the first run_id's count
    episodes += [_episode(r["run_id"], k, 0.5) for r in rows[16:] for k in range(4)]
    episodes.append(_episode(rows[0]["run_id"], 7, 0.0))  # alpha seed 0 only
    episodes.append({**_episode(rows[4]["run_id"], 0, 0.0), "seed": None})  # beta: no env seed, unpairable
    return results, pl.DataFrame(episodes)


def _scipy(a: np.ndarray, b: np.ndarray, level: float) -> tuple[float, float, float, float]:
    d = a - b
    low, high = stats.t.interval(level, len(d) - 1, loc=d.mean(), scale=stats.sem(d))
    return d.mean(), low, high, stats.ttest_rel(a, b).pvalue


def _call(low: float, high: float, lower_is_better: bool) -> str:
    if low <= 0 <= high:
        return "not resolved"
    return "a" if (high < 0) == lower_is_better else "b"


@pytest.mark.filterwarnings("ignore:Precision loss:RuntimeWarning")  # scipy, on beta - delta's near-equal seeds
@pytest.mark.parametrize("level", [0.95, 0.8])
def test_every_pair_matches_scipy_paired_t(level: float) -> None:
    results, rollouts = _tables()
    got = pairwise(results, rollouts, level=level)
    assert got.height == 6 and set(got["measure"]) == {"min_target_distance_m"}
    for r in got.iter_rows(named=True):
        a, b = r["encoder_a"], r["encoder_b"]
        assert a < b
        off = _scipy(np.array(EVAL_MSE[a]), np.array(EVAL_MSE[b]), level)
        near = {e: np.array([_near(e, s, k) for s in range(4) for k in range(4)]) for e in (a, b)}
        cl = _scipy(near[a], near[b], level)
        assert (r["seeds"], r["pairs"]) == (4, 16)
        assert (r["offline_difference"], r["offline_low"], r["offline_high"]) == pytest.approx(off[:3], abs=1e-12)
        assert (r["closed_difference"], r["closed_low"], r["closed_high"]) == pytest.approx(cl[:3], abs=1e-12)
        # an interval at `level` excludes 0 exactly when the paired t-test rejects at 1 - level
        assert (r["offline"] != "not resolved") == (off[3] < 1 - level)
        assert (r["closed"] != "not resolved") == (cl[3] < 1 - level)
        assert r["offline"] == _call(off[1], off[2], True) and r["closed"] == _call(cl[1], cl[2], True)


def test_the_verdicts_and_their_summary() -> None:
    results, rollouts = _tables()
    got = pairwise(results, rollouts)
    assert {(r["encoder_a"], r["encoder_b"]): r["verdict"] for r in got.iter_rows(named=True)} == EXPECTED
    assert got["note"].null_count() == got.height
    summary = pairwise_summary(got).row(0, named=True)
    assert (summary["encoder_pairs"], summary["resolved_by_both"], summary["agree"]) == (6, 4, 3)


def test_a_measure_where_higher_is_better_names_the_same_winners() -> None:
    """Lift here is 1 - closest approach: every difference changes sign and every call stays."""
    results, rollouts = _tables()
    near, lift = pairwise(results, rollouts), pairwise(results, rollouts, measure="target_lift_m")
    assert lift["closed_difference"].to_list() == pytest.approx((-near["closed_difference"]).to_list())
    assert lift["closed"].to_list() == near["closed"].to_list()
    assert lift["verdict"].to_list() == near["verdict"].to_list()


def test_sides_without_an_interval_say_why() -> None:
    """alpha and beta with one shared fit seed and no episodes at all; gamma and delta with every paired
    difference equal (a zero-width interval at 0.1 offline, at 0 in closed loop)."""
    rows = [row("smolvla", "libero_object", "alpha", 0, 1.0), row("smolvla", "libero_object", "beta", 0, 1.1),
            row("smolvla", "libero_object", "beta", 1, 1.1)]
    rows += [row("smolvla", "libero_object", e, s, 1.0 + 0.1 * (e == "gamma")) for e in ("gamma", "delta")
             for s in (0, 1)]
    results = table(rows)
    rollouts = pl.DataFrame([_episode(r["run_id"], k, 0.2) for r in rows[3:] for k in range(3)])
    got = {(r["encoder_a"], r["encoder_b"]): r for r in pairwise(results, rollouts).iter_rows(named=True)}
    one = got["alpha", "beta"]
    assert (one["seeds"], one["offline_difference"], one["offline_low"], one["offline"]) == (1, pytest.approx(-0.1),
                                                                                          None, None)
    assert (one["pairs"], one["closed_difference"], one["closed"], one["verdict"]) == (0, None, None, None)
    assert one["note"] == ("offline: 1 seeds both encoders have, an interval needs 2; closed loop: 0 pairs (fit "
                           "seed, episode key) both ran, an interval needs 2")
    flat = got["delta", "gamma"]
    assert (flat["offline_low"], flat["offline_high"], flat["offline"]) == (pytest.approx(-0.1), pytest.approx(-0.1),
                                                                            "a")
    assert (flat["pairs"], flat["closed_low"], flat["closed_high"], flat["closed"]) == (6, 0.0, 0.0, "not resolved")
    assert flat["verdict"] == "offline only" and "zero-width" in flat["note"]


def test_bad_arguments_are_one_line_errors() -> None:
    results, rollouts = _tables()
    with pytest.raises(GraftcacheError, match="measure 'closeness'"):
        pairwise(results, rollouts, measure="closeness")
    with pytest.raises(GraftcacheError, match="level 1.5"):
        pairwise(results, rollouts, level=1.5)
    with pytest.raises(GraftcacheError, match="rollouts table lacks column.s. max_steps"):
        pairwise(results, rollouts.drop("max_steps"))
    twice = pl.concat([results, results.head(1).with_columns(run_id=pl.lit("again"), policy_id=pl.lit("again"))])
    with pytest.raises(GraftcacheError, match="share smolvla/libero_object/alpha/none/seed 0"):
        pairwise(twice, rollouts)


def test_pairs_are_every_combination_of_candidate_encoders() -> None:
    results, rollouts = _tables()
    got = pairwise(results, rollouts)
    assert list(zip(got["encoder_a"], got["encoder_b"])) == list(itertools.combinations(sorted(EVAL_MSE), 2))
