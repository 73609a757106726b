"""The dose curves (graftcache.analysis.dose) on a hand table with known answers (tests/helpers/dose_tables.py),
recomputed with scipy.
"""

from __future__ import annotations

import numpy as np
import polars as pl
import pytest
from helpers.dose_tables import CONTROLS, EPISODE, JITTER, LOOP, OFFLINE, dose_tables
from helpers.tables import row, table
from scipy import stats

from graftcache import analysis as A
from graftcache.analysis.dose import dose_curves


def _rollouts(results: pl.DataFrame, episodes: pl.DataFrame, tmp_path) -> pl.DataFrame:
    path = tmp_path / "rollouts.parquet"
    episodes.write_parquet(path)
    return A.read_rollouts(path, results)


def _interval(values: np.ndarray) -> tuple[float, float, float]:
    ci = stats.ttest_1samp(values, 0.0).confidence_interval(0.95)
    return float(np.mean(values)), float(ci.low), float(ci.high)


def test_dose_curves_against_scipy(tmp_path) -> None:
    results, episodes = dose_tables()
    curves = dose_curves(results, _rollouts(results, episodes, tmp_path))
    points = curves.points.filter(pl.col("encoder") == "siglip").sort("dose")
    assert points["dose"].to_list() == list(CONTROLS)
    for p in points.iter_rows(named=True):
        d = list(CONTROLS).index(p["dose"])
        off = np.array(OFFLINE[p["dose"]])
        want = stats.t.interval(0.95, len(off) - 1, loc=off.mean(), scale=stats.sem(off))
        assert p["offline_mean"] == pytest.approx(off.mean())
        assert (p["offline_lo"], p["offline_hi"]) == pytest.approx(want)
        loop = np.array([LOOP[p["dose"]] + EPISODE[k] + JITTER[d, s, k] for s in range(3) for k in range(4)])
        assert (p["loop_mean"], p["loop_lo"], p["loop_hi"]) == pytest.approx(
            (loop.mean(), *stats.t.interval(0.95, len(loop) - 1, loc=loop.mean(), scale=stats.sem(loop))))
        assert (p["seeds"], p["episodes"]) == (3, 12)

    steps = curves.steps.filter(pl.col("encoder") == "siglip").sort("dose_from")
    doses = list(CONTROLS)
    for i, s in enumerate(steps.iter_rows(named=True)):
        lo, hi = doses[i], doses[i + 1]
        off = np.array(OFFLINE[hi]) - np.array(OFFLINE[lo])
        loop = np.array([LOOP[hi] - LOOP[lo] + JITTER[i + 1, seed, k] - JITTER[i, seed, k]
                         for seed in range(3) for k in range(4)])
        assert (s["offline_diff"], s["offline_lo"], s["offline_hi"]) == pytest.approx(_interval(off))
        assert (s["loop_diff"], s["loop_lo"], s["loop_hi"]) == pytest.approx(_interval(loop))
        assert (s["offline_pairs"], s["loop_pairs"]) == (3, 12)
    # known answers: the last step falls offline (so it is not confirmed: the loop rises), every other is confirmed
    assert steps["confirmed"].to_list() == [True, True, True, False]
    siglip = curves.curves.filter(pl.col("encoder") == "siglip").row(0, named=True)
    assert siglip["resolution"] == pytest.approx(0.02)
    assert (siglip["offline_monotone"], siglip["loop_monotone"]) == ("monotone within noise", "monotone")
    assert siglip["doses"] == 5 and siglip["note"] is None


def test_a_curve_without_its_own_blind_cells_or_rollouts() -> None:
    """dinov2-s: siglip's zero-image cells stand in at dose 1 (seed by seed); no rollouts: no resolution, a note."""
    results, _ = dose_tables()
    curves = dose_curves(results)
    dino = curves.points.filter(pl.col("encoder") == "dinov2-s").sort("dose")
    assert dino["dose"].to_list() == [0.0, 0.5, 1.0]
    assert dino["offline_mean"][-1] == pytest.approx(np.mean(OFFLINE[1.0]))
    assert dino["episodes"].to_list() == [0, 0, 0]
    line = curves.curves.filter(pl.col("encoder") == "dinov2-s").row(0, named=True)
    assert line["resolution"] is None and line["loop_monotone"] is None
    assert line["note"] == "no graded episodes: the closed loop was not measured"
    assert line["offline_monotone"] == "monotone"


def test_no_dose_rows_no_curves() -> None:
    results, _ = dose_tables()
    assert dose_curves(results.filter(~pl.col("control").str.starts_with("noise-"))) is None


def test_a_loop_resolved_against_offline_confirms_nothing(tmp_path) -> None:
    """The closed loop worsens clearly where offline improves clearly: resolved by both, confirmed by neither."""
    rows, episodes = [], []
    for control, mses, near in (("none", [1.2, 1.21, 1.19], 0.05), ("noise-0.5", [1.0, 1.01, 0.99], 0.30)):
        for seed, mse in enumerate(mses):
            r = row("smolvla", "libero_object", "siglip", seed, mse, control=control)
            rows.append(r)
            episodes += [{"run_id": r["run_id"], "success": False, "suite": "libero_object", "task_index": 0,
                          "episode": k, "seed": k, "max_steps": 40, "perturbation_m": 0.03,
                          "min_target_distance_m": near + k / 100 + seed / 1000} for k in range(3)]
    results = table(rows)
    curves = dose_curves(results, _rollouts(results, pl.DataFrame(episodes), tmp_path))
    step = curves.steps.row(0, named=True)
    assert step["offline_hi"] < 0 < step["loop_lo"] and step["confirmed"] is False
    line = curves.curves.row(0, named=True)
    assert line["resolution"] is None
    assert line["note"] == "no step confirmed by the closed loop at the 18 episodes spent"
    assert (line["offline_monotone"], line["loop_monotone"]) == ("not monotone", "monotone")
