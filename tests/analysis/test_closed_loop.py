"""`graftcache report --rollouts` (issue 31, item 5): offline scores against closed-loop success, on a hand-built
results table and rollouts, every figure worked out by hand below.

smolvla / libero_spatial, four cells (run_ids) with rollouts, proxy S = -score, success R:

    cell            eval_mse  eval_ci_mse  eval_mse_gripper  episodes  successes  R
    siglip seed 0   1.0       1.0          0.5               5         4          0.8
    siglip seed 1   2.0       3.0          0.5               5         3          0.6
    dinov2-s seed 0 3.0       2.0          0.5               5         4          0.8
    dinov2-s seed 1 4.0       4.0          0.5               5         1          0.2

eval_mse: the pair (siglip 1, dinov2-s 0) is violated: 2.0 < 3.0 but 0.6 < 0.8.
  MMRV = (1/N) sum_i max_j |R_i - R_j| [(S_i < S_j) != (R_i < R_j)]: siglip 0 is first on both sides (0);
  siglip 1's worst violation is with dinov2-s 0, |0.6 - 0.8| = 0.2; dinov2-s 0's with siglip 1 (0.2; with siglip 0
  it is "violated" too, S differ and R tie, at weight |0.8 - 0.8| = 0); dinov2-s 1 is last on both (0):
  MMRV = (0 + 0.2 + 0.2 + 0) / 4 = 0.1.
  Spearman: ranks of -score (4, 3, 2, 1), of R (3.5, 2, 3.5, 1) (tied 0.8s share 3.5); centred (1.5, .5, -.5, -1.5)
  and (1, -.5, 1, -1.5): sum of products 3, sums of squares 5 and 4.5: rho = 3 / sqrt(22.5) = sqrt(0.4).
  Kendall tau-b: of the 6 pairs 4 concordant, 1 discordant (the violated one), 1 tied in R only:
  (4 - 1) / sqrt(6 * 5) = 3 / sqrt(30).
eval_ci_mse orders them 1.0, 2.0, 3.0, 4.0 = siglip 0, dinov2-s 0, siglip 1, dinov2-s 1: no pair is ordered against
  success (only the R tie, at weight 0): MMRV = 0; rho: ranks (4, 2, 3, 1) vs (3.5, 2, 3.5, 1), centred products
  1.5 + .25 + .5 + 2.25 = 4.5 over sqrt(5 * 4.5): rho = sqrt(0.9); tau-b = 5 / sqrt(30).
eval_mse_gripper: every cell 0.5, so rho and tau-b are undefined, while MMRV counts each pair R orders as violated
  (S_i < S_j is never true): siglip 1 -> 0.2 (vs the 0.8s), dinov2-s 1 -> 0.6, the 0.8s -> 0: MMRV = 0.8 / 4 = 0.2.
eval_mse_arm: null in every row (format 3 rows): 0 cells, all undefined.
smolvla / libero_object: three cells, every episode failed: success 0 everywhere -> all undefined.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import polars as pl
import pytest
from helpers.tables import row, table

from graftcache import analysis, report
from graftcache.cli import main
from graftcache.errors import GraftcacheError

Z = 1.959963984540054  # the two-sided 95% normal quantile, written out


def _results() -> pl.DataFrame:
    spatial = [("siglip", 0, 1.0, 1.0), ("siglip", 1, 2.0, 3.0), ("dinov2-s", 0, 3.0, 2.0), ("dinov2-s", 1, 4.0, 4.0)]
    scores = {"eval_mse_gripper": 0.5, "eval_mse_arm": None}
    rows = [row("smolvla", "libero_spatial", e, s, mse, eval_ci_mse=ci, **scores) for e, s, mse, ci in spatial]
    rows += [row("smolvla", "libero_object", e, s, 1.0 + s + (e == "dinov2-s"), eval_ci_mse=2.0, **scores)
             for e in ("siglip", "dinov2-s") for s in (0, 1)]
    return table(rows)


SUCCESSES = {("libero_spatial", "siglip", 0): 4, ("libero_spatial", "siglip", 1): 3,
             ("libero_spatial", "dinov2-s", 0): 4, ("libero_spatial", "dinov2-s", 1): 1,
             ("libero_object", "siglip", 0): 0, ("libero_object", "siglip", 1): 0, ("libero_object", "dinov2-s", 0): 0}


def _rollouts(results: pl.DataFrame) -> pl.DataFrame:
    """5 episodes per rolled-out cell, `SUCCESSES` of them successful; libero_object dinov2-s seed 1 not rolled
    out. Columns past run_id and success are provenance, as `graftcache rollout` writes them."""
    ids = {(r["suite"], r["encoder"], r["seed"]): r["run_id"] for r in results.iter_rows(named=True)}
    episodes = [{"run_id": ids[key], "suite": key[0], "task_index": 0, "episode": k, "seed": 100 + k,
                 "success": k < wins, "steps": 220, "seconds": 3.5}
                for key, wins in SUCCESSES.items() for k in range(5)]
    return pl.DataFrame(episodes)


@pytest.fixture
def files(tmp_path: Path) -> tuple[Path, Path]:
    results = _results()
    results.write_parquet(tmp_path / "results.parquet")
    _rollouts(results).write_parquet(tmp_path / "rollouts.parquet")
    return tmp_path / "results.parquet", tmp_path / "rollouts.parquet"


def _wilson_by_quadratic(k: int, n: int) -> tuple[float, float]:
    """The Wilson interval as the p where (k/n - p)^2 = z^2 p (1 - p) / n: the roots of
    (1 + z^2/n) p^2 - (2 k/n + z^2/n) p + (k/n)^2 = 0."""
    p, q = k / n, Z * Z / n
    lo, hi = sorted(np.roots([1 + q, -(2 * p + q), p * p]).real)
    return lo, hi


@pytest.mark.parametrize(("k", "n"), [(4, 5), (3, 5), (1, 5), (0, 5), (5, 5), (17, 50)])
def test_the_wilson_interval_is_the_roots_of_its_quadratic(k: int, n: int) -> None:
    assert analysis.wilson(k, n) == pytest.approx(_wilson_by_quadratic(k, n), abs=1e-12)


def test_the_wilson_interval_holds_its_rate_to_the_last_bit() -> None:
    """At 0 or n successes the bound is the rate exactly, which the formula misses by an ulp for some n (0 of 10:
    a low bound of 2.8e-17 above a rate of 0, drawn as a negative error bar)."""
    for n in range(1, 101):
        for k in range(n + 1):
            lo, hi = analysis.wilson(k, n)
            assert 0 <= lo <= k / n <= hi <= 1, (k, n, lo, hi)
    assert analysis.wilson(0, 10)[0] == 0 and analysis.wilson(13, 13)[1] == 1


def test_a_report_draws_every_rate_with_ten_episodes_a_cell(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """Success rates of 0.8, 0.9, 0.5, 0.4 and 0.1 over 10 episodes on one backbone, every episode failed on another:
    the report and its closed-loop figure are written (matplotlib refused the error bars of 0 of 10 before)."""
    rates = {("smolvla", "siglip", 0): 8, ("smolvla", "siglip", 1): 9, ("smolvla", "dinov2-s", 0): 5,
             ("smolvla", "dinov2-s", 1): 4, ("smolvla", "resnet18", 0): 1}
    rows = [row(b, "libero_spatial", e, s, 1.0 + i) for i, (b, e, s) in enumerate(rates)]
    rows += [row("pi05", "libero_spatial", e, s, 2.0 + i) for i, (_, e, s) in enumerate(rates)]
    results = table(rows)
    wins = {r["run_id"]: rates.get((r["backbone"], r["encoder"], r["seed"]), 0) if r["backbone"] == "smolvla" else 0
            for r in results.iter_rows(named=True)}
    results.write_parquet(tmp_path / "results.parquet")
    pl.DataFrame([{"run_id": run, "suite": "libero_spatial", "task_index": 0, "episode": k, "seed": 100 + k,
                   "success": k < n, "steps": 220, "seconds": 3.5} for run, n in wins.items() for k in range(10)]
                 ).write_parquet(tmp_path / "rollouts.parquet")
    code = main(["report", str(tmp_path / "results.parquet"), "--rollouts", str(tmp_path / "rollouts.parquet"),
                 "--out", str(tmp_path / "report")])
    assert code == 0, capsys.readouterr().err[-2000:]
    assert (tmp_path / "report" / "closed_loop.png").stat().st_size > 0


def test_rank_statistics_match_the_hand_computed_values() -> None:
    score, success = [1.0, 2.0, 3.0, 4.0], [0.8, 0.6, 0.8, 0.2]
    minus = [-s for s in score]
    assert analysis.spearman(minus, success) == pytest.approx(math.sqrt(0.4))
    assert analysis.tau_b(minus, success) == pytest.approx(3 / math.sqrt(30))
    assert analysis.mmrv(score, success) == pytest.approx(0.1)
    assert analysis.mmrv([1.0, 2.0, 3.0, 4.0], [1.0, 0.5, 0.5, 0.0]) == 0  # ordered alike: nothing violated
    assert analysis.spearman([1.0, 1.0], [0.0, 1.0]) is None and analysis.spearman([1.0], [1.0]) is None


def test_cells_and_agreement_on_the_hand_built_tables(files: tuple[Path, Path]) -> None:
    results = analysis.analyze(pl.read_parquet(files[0]))
    loop = analysis.closed_loop(results.results, analysis.read_rollouts(files[1], results.results))
    cells = loop.cells
    assert cells.height == 7 and set(cells.columns) == set(analysis.CELL_SCHEMA)
    four = cells.filter(pl.col("suite") == "libero_spatial", pl.col("encoder") == "siglip", pl.col("seed") == 0)
    assert four.select("episodes", "successes", "success_rate").row(0) == (5, 4, 0.8)
    assert four.select("ci_low", "ci_high").row(0) == pytest.approx(_wilson_by_quadratic(4, 5))

    got = {(r["suite"], r["score"]): r for r in loop.agreement.filter(pl.col("measure") == "success").iter_rows(
        named=True)}
    want = {"eval_mse": (4, math.sqrt(0.4), 3 / math.sqrt(30), 0.1),
            "eval_ci_mse": (4, math.sqrt(0.9), 5 / math.sqrt(30), 0.0),
            "eval_mse_gripper": (4, None, None, 0.2), "eval_mse_arm": (0, None, None, None)}
    for score, (n, rho, tau, worst) in want.items():
        r = got["libero_spatial", score]
        assert r["cells"] == n, score
        assert (r["spearman"], r["kendall_tau_b"], r["mmrv"]) == pytest.approx((rho, tau, worst)), score
    assert got["libero_spatial", "eval_mse"]["note"] is None
    assert got["libero_spatial", "eval_mse_gripper"]["note"] == "every cell has the same eval_mse_gripper: rho and " \
                                                                "tau-b undefined"
    assert got["libero_spatial", "eval_mse_arm"]["note"] == "no cell with rollouts has a finite eval_mse_arm"
    for score in analysis.CLOSED_LOOP_SCORES:  # all-fail suite: nothing is a number
        r = got["libero_object", score]
        assert (r["spearman"], r["kendall_tau_b"], r["mmrv"]) == (None, None, None)
    assert got["libero_object", "eval_mse"]["cells"] == 3
    assert got["libero_object", "eval_mse"]["note"] == "every cell's success rate is 0%: no order to agree with"


def test_report_rollouts_end_to_end(files: tuple[Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    out = tmp_path / "out"
    assert main(["report", str(files[0]), "--out", str(out), "--rollouts", str(files[1])]) == 0
    assert str(out / "closed_loop.csv") in capsys.readouterr().out
    csv = pl.read_csv(out / "closed_loop.csv", schema=report.CLOSED_LOOP_CSV_SCHEMA)
    assert tuple(csv.columns) == report.CLOSED_LOOP_CSV_COLUMNS == (
        "backbone", "suite", "cells_of", "score", "measure", "cells", "spearman", "spearman_low", "spearman_high",
        "kendall_tau_b", "kendall_tau_b_low", "kendall_tau_b_high", "mmrv", "mmrv_low", "mmrv_high", "replicates")
    success = csv.filter(pl.col("measure") == "success")
    spatial = success.filter(pl.col("suite") == "libero_spatial", pl.col("score") == "eval_mse",
                             pl.col("cells_of") == "candidates").row(0, named=True)
    assert (spatial["cells"], spatial["spearman"], spatial["kendall_tau_b"], spatial["mmrv"]) == pytest.approx(
        (4, math.sqrt(0.4), 3 / math.sqrt(30), 0.1))
    for name in ("spearman", "kendall_tau_b", "mmrv"):  # an interval around each figure, from cells and episodes
        assert spatial[f"{name}_low"] <= spatial[name] <= spatial[f"{name}_high"], name
        assert spatial[f"{name}_low"] < spatial[f"{name}_high"], name
    failed = success.filter(pl.col("suite") == "libero_object")
    assert failed.height == 8 and failed.select("spearman", "kendall_tau_b", "mmrv").null_count().row(0) == (8, 8, 8)
    assert "libero_object,candidates,eval_mse,success,3" + "," * 10 + "\n" in (out / "closed_loop.csv").read_text()
    graded = csv.filter(pl.col("measure") != "success")  # these rollouts have no graded columns: kept, undefined
    assert graded.height == 2 * 2 * 4 * 5 and graded["cells"].to_list() == [0] * 80
    assert graded.select("spearman", "kendall_tau_b", "mmrv").null_count().row(0) == (80, 80, 80)
    md = (out / "report.md").read_text()
    assert "## Offline scores vs closed-loop success" in md
    assert "Agreement is computed over policies, not over seed means" in md
    assert ("| SmolVLA | libero_object | candidates | success | `eval_mse` | 3 | — | — | — | every cell's success rate "
            "is 0%: no order to agree with |") in md
    assert "undefined, never 0" in md
    assert "80% [38%, 96%]" in md  # 4 of 5 with its Wilson interval
    assert ("The graded measures are unavailable for these rollouts: none of the 35 episodes records them "
            "(format-1 rollouts rows, or a table without the graded columns)") in md
    assert ("SmolVLA · libero_spatial · candidates: undefined over 0 cells (graded measures unavailable: no rollout of "
            "these cells records min_target_distance_m (format-1 rows, or a table without it)).") in md
    assert "| closest approach" not in md  # no graded column in the cells table when no cell has one
    assert (out / "closed_loop.png").is_file()
    assert main(["report", str(files[0]), "--out", str(out)]) == 0  # without rollouts: no stale closed-loop files
    assert not (out / "closed_loop.csv").exists() and not (out / "closed_loop.png").exists()
    assert not (out / "pairwise.csv").exists()
    assert "## Offline scores vs closed-loop success" not in (out / "report.md").read_text()


def test_bad_rollouts_are_refused_in_one_line_naming_the_file(files: tuple[Path, Path], tmp_path: Path) -> None:
    results = analysis.analyze(pl.read_parquet(files[0])).results
    episodes = pl.read_parquet(files[1])
    cases = {
        "foreign": (episodes.with_columns(pl.lit("0123456789abcdef").alias("run_id")),
                    "1 run_id(s) not in the results table, e.g. 0123456789abcdef: pass the results file whose rows "
                    "were rolled out"),
        "no_success": (episodes.drop("success"),
                       "rollouts table lacks column(s) success (the report needs run_id, success per episode)"),
        "counts": (episodes.with_columns(pl.lit(2).alias("success")),
                   "column success holds Int32 values such as 2, not true/false"),
    }
    for name, (frame, line) in cases.items():
        path = tmp_path / f"{name}.parquet"
        frame.write_parquet(path)
        with pytest.raises(GraftcacheError) as refused:
            analysis.read_rollouts(path, results)
        assert str(refused.value) == f"{path}: {line}", name
    ones = tmp_path / "ones.parquet"  # 0/1 integers, as other tools may write them, read as booleans
    episodes.with_columns(pl.col("success").cast(pl.Int64)).write_parquet(ones)
    assert analysis.read_rollouts(ones, results)["success"].to_list() == episodes["success"].to_list()
