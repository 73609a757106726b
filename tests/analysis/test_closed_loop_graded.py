"""Issue 43, item 4: the graded closed-loop measures in the analysis, on hand-built cells and episodes.

smolvla / libero_object, six cells and four episodes each (EPISODES below; one value per episode):

    cell              eval_mse  closest approach (m)          lift (m)              grasped        goal
    siglip seed 0     1.0       .05 .07 .06 .06  (mean .06)   .10 .00 .08 .06       1 0 1 1        1 .5 .5 0
    siglip seed 1     1.2       .09 .11 .10 .14  (.11)        .00 .02 .00 .02       0 0 0 1        0 0 .5 .5
    dinov2-s seed 0   1.1       .11 .13 .12 .12  (.12)        .04 .00 .00 .00       0 1 0 0        .5 0 0 0
    dinov2-s seed 1   1.5       .20 .18 .22 .20  (.20)        .00 .00 .00 .00       0 0 0 0        0 0 0 0
    resnet18 seed 0   1.3       .12 .16 .14 .14  (.14)        .00 .01 .00 .00       0 0 0 0        0 0 0 .5
    zero-image        2.0       .30 .32 .31 .31  (.31)        .00 .00 .00 .00       0 0 0 0        0 0 0 0

Every agreement figure is recomputed here with scipy (Spearman, Kendall's tau-b) and a double loop (MMRV) on the
cell means, with every measure oriented so that higher is better; the intervals against replicates drawn by hand
with the same generators and scored by scipy.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import polars as pl
import pytest
from helpers.tables import row, table
from scipy import stats

from graftcache import analysis as A
from graftcache.analysis.closed_loop_boot import mmrv_rows, spearman_rows, tau_b_rows, two_level
from graftcache.analysis.stats import generator
from graftcache.errors import GraftcacheError

CELLS = [("siglip", 0, "none", 1.0), ("siglip", 1, "none", 1.2), ("dinov2-s", 0, "none", 1.1),
         ("dinov2-s", 1, "none", 1.5), ("resnet18", 0, "none", 1.3), ("siglip", 0, "zero-image", 2.0)]
EPISODES = {
    "min_target_distance_m": [[.05, .07, .06, .06], [.09, .11, .10, .14], [.11, .13, .12, .12], [.20, .18, .22, .20],
                              [.12, .16, .14, .14], [.30, .32, .31, .31]],
    "target_lift_m": [[.10, 0, .08, .06], [0, .02, 0, .02], [.04, 0, 0, 0], [0] * 4, [0, .01, 0, 0], [0] * 4],
    "grasped": [[1, 0, 1, 1], [0, 0, 0, 1], [0, 1, 0, 0], [0] * 4, [0] * 4, [0] * 4],
    "goal_fraction": [[1, .5, .5, 0], [0, 0, .5, .5], [.5, 0, 0, 0], [0] * 4, [0, 0, 0, .5], [0] * 4],
}
SUCCESS = [[1, 0, 0, 0], [0] * 4, [0, 1, 0, 0], [0] * 4, [0] * 4, [0] * 4]


def _results() -> pl.DataFrame:
    rows = [row("smolvla", "libero_object", e, s, mse, control=c) for e, s, c, mse in CELLS]
    return A.analyze(table(rows)).results


def _episodes(results: pl.DataFrame) -> pl.DataFrame:
    """Format-2 rows (graded columns and the whole key) for CELLS, in its order; final distance = closest + 0.1."""
    ids = results.sort("backbone", "suite", "encoder", "control", "seed")
    by_cell = {(r["encoder"], r["seed"], r["control"]): r["run_id"] for r in ids.iter_rows(named=True)}
    out = []
    for i, (encoder, seed, control, _) in enumerate(CELLS):
        for k in range(4):
            out.append({"run_id": by_cell[encoder, seed, control], "suite": "libero_object", "task_index": 0,
                        "episode": k, "seed": 1000 + k, "max_steps": 60, "perturbation_m": 0.03,
                        "success": bool(SUCCESS[i][k]), **_graded(i, k), "target": "alphabet_soup_1", "steps": 60})
    return pl.DataFrame(out)


def _graded(i: int, k: int) -> dict:
    """Episode k of CELLS[i]'s graded values."""
    near = EPISODES["min_target_distance_m"][i][k]
    return {"min_target_distance_m": near, "final_target_distance_m": near + 0.1,
            "target_lift_m": float(EPISODES["target_lift_m"][i][k]), "grasped": bool(EPISODES["grasped"][i][k]),
            "goal_fraction": float(EPISODES["goal_fraction"][i][k])}


@pytest.fixture
def loop(tmp_path: Path) -> A.ClosedLoop:
    results = _results()
    _episodes(results).write_parquet(tmp_path / "rollouts.parquet")
    return A.closed_loop(results, A.read_rollouts(tmp_path / "rollouts.parquet", results))


def _means(measure: str) -> np.ndarray:
    if measure == "final_target_distance_m":
        values = [[v + 0.1 for v in cell] for cell in EPISODES["min_target_distance_m"]]
    else:
        values = SUCCESS if measure == "success" else EPISODES[measure]
    return np.array([np.mean(v) for v in values], dtype=np.float64)


def _mmrv_by_loops(score: np.ndarray, good: np.ndarray) -> float:
    """SIMPLER's MMRV written out: each cell's worst misordering, weighted by the gap in the measure."""
    worst = []
    for i in range(len(score)):
        worst.append(max(abs(good[i] - good[j]) * ((-score[i] < -score[j]) != (good[i] < good[j]))
                         for j in range(len(score))))
    return sum(worst) / len(worst)


def test_a_format_2_table_reads_its_graded_columns_and_key_typed(loop: A.ClosedLoop) -> None:
    r = loop.rollouts
    assert set(A.GRADED_MEASURES) | set(A.PAIR_KEY) | set(A.PROVENANCE) | {"run_id", "success", "policy_key"} == set(
        r.columns)
    assert r["kernels"].null_count() == len(r)  # a format-2 table records none
    assert r.schema["grasped"] == pl.Boolean and r.schema["episode"] == pl.Int64
    assert r["min_target_distance_m"].to_list()[:4] == EPISODES["min_target_distance_m"][0]
    assert loop.ungraded == 0


def test_cells_hold_each_measure_s_mean_over_its_episodes(loop: A.ClosedLoop) -> None:
    cells = loop.cells.sort("eval_mse")  # CELLS by score: 1.0, 1.1, 1.2, 1.3, 1.5, 2.0
    order = np.argsort([mse for *_, mse in CELLS])
    for measure in A.MEASURES:
        assert cells[A.MEASURE_COLUMNS[measure]].to_numpy() == pytest.approx(_means(measure)[order]), measure
    assert cells["graded_episodes"].to_list() == [4] * 6


def _zero_share(cells: list[list[float]]) -> float:
    """The chance that one slot of a replicate (a cell drawn at random, then its 4 episodes with replacement) has
    a mean of 0, for measures >= 0."""
    return float(np.mean([(np.mean(np.asarray(c) == 0)) ** 4 for c in cells]))


@pytest.mark.parametrize("measure", A.MEASURES)
def test_agreement_is_scipy_s_on_the_cell_means_oriented_better_is_higher(loop: A.ClosedLoop, measure: str) -> None:
    score = np.array([mse for *_, mse in CELLS])
    good = _means(measure) * (1 if A.HIGHER_IS_BETTER[measure] else -1)
    r = loop.agreement.filter(pl.col("cells_of") == "with controls", pl.col("score") == "eval_mse",
                              pl.col("measure") == measure).row(0, named=True)
    assert r["cells"] == 6
    if measure == "success":  # a replicate has no order where each of its 6 drawn cells' 4 redrawn episodes fail
        tied = _zero_share(SUCCESS) ** 6
        assert abs(r["replicates"] - 1000 * (1 - tied)) < 4 * math.sqrt(1000 * tied * (1 - tied))
        assert r["note"] == (f"intervals over only {r['replicates']} of 1000 replicates (in the others every drawn "
                             "cell had one success: no order)")
    else:  # every cell ties in a replicate mostly by drawing all zeros in every drawn cell
        assert r["replicates"] >= 900 and (r["note"] is None) == (r["replicates"] >= 950)
    assert r["spearman"] == pytest.approx(stats.spearmanr(-score, good).statistic)
    assert r["kendall_tau_b"] == pytest.approx(stats.kendalltau(-score, good, variant="b").statistic)
    assert r["mmrv"] == pytest.approx(_mmrv_by_loops(score, good))
    if measure == "min_target_distance_m":  # closest approach follows eval_mse except siglip 1 / dinov2-s 0
        assert r["spearman"] == pytest.approx(1 - 6 * 2 / (6 * 35)) and r["kendall_tau_b"] == pytest.approx(13 / 15)


def test_the_candidates_agreement_leaves_the_controls_out(loop: A.ClosedLoop) -> None:
    """The five plain cells alone: closest approach .06 .12 .11 .14 .20 at eval_mse 1.0 1.1 1.2 1.3 1.5."""
    r = loop.agreement.filter(pl.col("cells_of") == "candidates", pl.col("score") == "eval_mse",
                              pl.col("measure") == "min_target_distance_m").row(0, named=True)
    score, near = np.array([1.0, 1.1, 1.2, 1.3, 1.5]), np.array([.06, .12, .11, .14, .20])
    assert r["cells"] == 5
    assert r["spearman"] == pytest.approx(stats.spearmanr(-score, -near).statistic) == pytest.approx(0.9)
    assert r["kendall_tau_b"] == pytest.approx(stats.kendalltau(-score, -near, variant="b").statistic)


def _two_level_by_hand(score: np.ndarray, episodes: list[np.ndarray], rng: np.random.Generator) -> np.ndarray:
    """The documented replicates, drawn one slot at a time: (1000, 3) of rho, tau-b and MMRV (scipy and loops),
    NaN where the drawn cells all tie. The generator is used in the documented order: first the cells of every
    replicate, then, cell by cell, the episodes of each slot that drew it, in replicate order."""
    picks = rng.integers(0, len(score), size=(A.N_BOOT, len(score)))
    means = np.empty(picks.shape)
    for cell, values in enumerate(episodes):
        slots = np.nonzero(picks == cell)
        draws = rng.integers(0, len(values), size=(len(slots[0]), len(values)))
        for (b, i), draw in zip(zip(*slots), draws):
            means[b, i] = values[draw].mean()
    out = np.full((A.N_BOOT, 3), np.nan)
    for b in range(A.N_BOOT):
        x, y = score[picks[b]], -means[b]
        if np.ptp(y) == 0:
            continue
        with np.errstate(invalid="ignore", divide="ignore"):
            out[b] = (stats.spearmanr(-x, y).statistic, stats.kendalltau(-x, y, variant="b").statistic,
                      _mmrv_by_loops(x, y))
    return out


def test_the_intervals_are_symmetric_over_cell_and_episode_replicates(loop: A.ClosedLoop) -> None:
    """Replicates drawn here slot by slot: each replicate redraws the cells (in policy order) with replacement,
    then each drawn cell's episodes (sorted), from the generator seeded by (seed 0, the group, the set of cells,
    the score, the measure); each replicate's figures from scipy; the interval is the figure +- the 95% quantile
    of |replicate - figure|, clipped to the statistic's range."""
    measure = "min_target_distance_m"
    cells = loop.cells.sort("policy_key")
    index = {(e, s, c): i for i, (e, s, c, _) in enumerate(CELLS)}
    order = [index[e, s, c] for e, s, c in cells.select("encoder", "seed", "control").iter_rows()]
    score = np.array([CELLS[i][3] for i in order])
    episodes = [np.sort(EPISODES[measure][i]) for i in order]
    rng = generator(0, "closed-loop", "smolvla", "libero_object", "with controls", "eval_mse", measure)
    reps = _two_level_by_hand(score, episodes, rng)
    r = loop.agreement.filter(pl.col("cells_of") == "with controls", pl.col("score") == "eval_mse",
                              pl.col("measure") == measure).row(0, named=True)
    assert r["replicates"] == int(np.isfinite(reps[:, 2]).sum())
    for k, (name, low, high) in enumerate((("spearman", -1, 1), ("kendall_tau_b", -1, 1), ("mmrv", 0, math.inf))):
        draws = reps[:, k][np.isfinite(reps[:, k])]
        half = np.quantile(np.abs(draws - r[name]), 0.95)
        assert (r[f"{name}_low"], r[f"{name}_high"]) == pytest.approx(
            (max(low, r[name] - half), min(high, r[name] + half))), name


def test_the_vectorised_statistics_are_scipy_s_row_by_row_ties_included() -> None:
    rng = np.random.default_rng(3)
    x = rng.integers(0, 4, size=(50, 7)).astype(np.float64)  # ties on both sides
    rows = rng.integers(0, 3, size=(50, 7)).astype(np.float64)
    keep = (np.ptp(rows, axis=1) > 0) & (np.ptp(x, axis=1) > 0)
    x, rows = x[keep], rows[keep]
    assert spearman_rows(x, rows) == pytest.approx([stats.spearmanr(a, b).statistic for a, b in zip(x, rows)])
    assert tau_b_rows(x, rows) == pytest.approx([stats.kendalltau(a, b, variant="b").statistic
                                                 for a, b in zip(x, rows)])
    assert mmrv_rows(x, rows) == pytest.approx([A.mmrv(a, b) for a, b in zip(x, rows)])


def _spread_cells(tmp_path: Path, mus: list[float], n: int, spread: float) -> dict:
    """Plain cells e0, e1, ... at eval_mse 1.0, 1.1, ... whose closest approaches are mu +- an even spread over n
    episodes; their candidates agreement of eval_mse and the closest approach."""
    rows = [row("smolvla", "libero_object", f"e{i}", 0, 1.0 + 0.1 * i) for i in range(len(mus))]
    results = A.analyze(table(rows)).results
    offsets = np.linspace(-spread, spread, n)
    pl.DataFrame([{"run_id": r["run_id"], "success": False, "min_target_distance_m": float(mu + o)}
                  for r, mu in zip(rows, mus) for o in offsets]).write_parquet(tmp_path / f"{n}.parquet")
    loop = A.closed_loop(results, A.read_rollouts(tmp_path / f"{n}.parquet", results))
    return loop.agreement.filter(pl.col("cells_of") == "candidates", pl.col("score") == "eval_mse",
                                 pl.col("measure") == "min_target_distance_m").row(0, named=True)


@pytest.mark.parametrize(("mus", "n", "spread"), [
    ([0.10, 0.15, 0.12, 0.19, 0.14, 0.21], 4, 0.04), ([0.10, 0.15, 0.12, 0.19, 0.14, 0.21], 40, 0.04),
    ([0.10, 0.11, 0.12, 0.13], 4, 0.03), ([0.10 + 0.01 * i for i in range(8)], 2, 0.05),  # ordered, noisy
    ([0.10, 0.20], 6, 0.0), ([0.50, 0.30, 0.40], 3, 0.2), ([0.1, 0.1, 0.1, 0.2], 5, 0.01)])
def test_every_interval_holds_its_figure(tmp_path: Path, mus: list[float], n: int, spread: float) -> None:
    r = _spread_cells(tmp_path, mus, n, spread)
    for name in A.STATISTICS:
        assert r[f"{name}_low"] <= r[name] <= r[f"{name}_high"], name


def test_a_perfect_order_without_episode_noise_has_a_point_interval(tmp_path: Path) -> None:
    """Two cells, each with identical episodes, in the order of their scores: every replicate that draws both is
    perfectly ordered (rho = tau-b = 1, MMRV = 0); one that draws one cell twice has no order and is left out."""
    r = _spread_cells(tmp_path, [0.10, 0.20], 6, 0.0)
    picks = generator(0, "closed-loop", "smolvla", "libero_object", "candidates", "eval_mse",
                      "min_target_distance_m").integers(0, 2, size=(A.N_BOOT, 2))
    assert r["replicates"] == int((picks[:, 0] != picks[:, 1]).sum())
    assert [r[f"spearman{p}"] for p in ("", "_low", "_high")] == pytest.approx([1.0, 1.0, 1.0], abs=1e-12)
    assert [r[f"mmrv{p}"] for p in ("", "_low", "_high")] == [0.0, 0.0, 0.0]


def test_where_the_replicates_lie_above_the_figure_the_interval_still_holds_it(tmp_path: Path) -> None:
    """Eight cells 1 cm apart in the order of their scores, each episode +-5 cm: MMRV is 0, and redrawn episodes
    can only misorder the cells, so the replicates' 2.5th percentile lies above 0 (a percentile interval would
    leave out its own figure); the symmetric interval starts at 0, and rho's ends at its figure, 1."""
    mus = [0.10 + 0.01 * i for i in range(8)]
    r = _spread_cells(tmp_path, mus, 4, 0.05)
    rng = generator(0, "closed-loop", "smolvla", "libero_object", "candidates", "eval_mse", "min_target_distance_m")
    episodes = [np.sort(mu + np.linspace(-0.05, 0.05, 4)) for mu in mus]
    picks, means = two_level(episodes, rng)
    score = 1.0 + 0.1 * np.arange(8)
    assert np.percentile(mmrv_rows(score[picks], -means), 2.5) > 0.001
    assert r["mmrv"] == 0.0 and r["mmrv_low"] == 0.0 and r["mmrv_high"] > 0.01
    assert r["spearman"] == pytest.approx(1.0) and r["spearman_high"] == 1.0 and r["spearman_low"] < 0.9


def test_degenerate_agreement_is_null_with_its_reason(tmp_path: Path) -> None:
    results = _results()
    episodes = _episodes(results).with_columns(
        min_target_distance_m=pl.lit(0.1), grasped=pl.lit(None, dtype=pl.Boolean))
    one = results.filter(pl.col("encoder") == "resnet18")["run_id"][0]
    episodes = episodes.with_columns(goal_fraction=pl.when(pl.col("run_id") == one).then(0.5).otherwise(None))
    episodes.write_parquet(tmp_path / "r.parquet")
    loop = A.closed_loop(results, A.read_rollouts(tmp_path / "r.parquet", results))
    got = {r["measure"]: r for r in loop.agreement.filter(pl.col("cells_of") == "with controls",
                                                          pl.col("score") == "eval_mse").iter_rows(named=True)}
    notes = {m: got[m]["note"] for m in ("min_target_distance_m", "grasped", "goal_fraction")}
    assert notes == {
        "min_target_distance_m": "every cell's min_target_distance_m is 0.1: no order to agree with",
        "grasped": "graded measures unavailable: no rollout of these cells records grasped (format-1 rows, or a "
                   "table without it)",
        "goal_fraction": "1 cell: agreement needs 2 or more",
    }
    for m in notes:
        assert [got[m][c] for c in AGREEMENT_FIGURES] == [None] * len(AGREEMENT_FIGURES), m
    assert got["target_lift_m"]["note"] is None and got["target_lift_m"]["spearman_low"] is not None


AGREEMENT_FIGURES = [f"{s}{part}" for s in A.STATISTICS for part in ("", "_low", "_high")]


def test_a_format_1_file_reads_with_graded_measures_null(tmp_path: Path) -> None:
    """A format-1 rollouts file (graftcache.rollout.rollouts_file format 1: no graded columns, no perturbation_m)."""
    results = _results()
    format_1 = _episodes(results).select(
        pl.format("{}-{}", "run_id", "episode").alias("episode_id"), pl.lit(1).alias("format_version"), "run_id",
        "suite", "task_index", "episode", "seed", pl.col("episode").alias("init_state"), "max_steps", "success",
        "steps", pl.lit(1.5).alias("seconds"), pl.lit(None, dtype=pl.String).alias("video"))
    format_1.write_parquet(tmp_path / "old.parquet")
    read = A.read_rollouts(tmp_path / "old.parquet", results)
    assert read.select(*A.GRADED_MEASURES, "perturbation_m").null_count().row(0) == (24,) * 6
    assert read["episode"].to_list() == format_1["episode"].to_list()
    loop = A.closed_loop(results, read)
    assert loop.ungraded == 24 and loop.cells["graded_episodes"].to_list() == [0] * 6
    graded = loop.agreement.filter(pl.col("measure") != "success")
    assert graded.height == 2 * 5 * 4 and graded["spearman"].null_count() == 40
    assert set(graded["note"]) == {f"graded measures unavailable: no rollout of these cells records {m} (format-1 "
                                   "rows, or a table without it)" for m in A.GRADED_MEASURES}
    success = loop.agreement.filter(pl.col("cells_of") == "with controls", pl.col("measure") == "success",
                                    pl.col("score") == "eval_mse").row(0, named=True)
    score = np.array([mse for *_, mse in CELLS])
    assert success["spearman"] == pytest.approx(stats.spearmanr(-score, _means("success")).statistic)


def test_odd_graded_columns_are_refused_in_one_line_naming_the_file(tmp_path: Path) -> None:
    results = _results()
    episodes = _episodes(results)
    cases = {
        "text": (episodes.with_columns(pl.col("min_target_distance_m").cast(pl.String)),
                 "column min_target_distance_m holds String values, not Float64"),
        "nan": (episodes.with_columns(target_lift_m=pl.lit(math.nan)),
                "non-finite values in column(s) target_lift_m (null: not measured)"),
        "counts": (episodes.with_columns(pl.lit(2).alias("grasped")),
                   "column grasped holds Int32 values such as 2, not true/false"),
        "episode": (episodes.with_columns(pl.col("episode").cast(pl.Float64)),
                    "column episode holds Float64 values, not Int64"),
        "closer": (episodes.with_columns(min_target_distance_m=pl.lit(-0.27)),
                   "column min_target_distance_m holds -0.27, not a possible value (the measure is >= 0; "
                   "graftcache.rollout.graded)"),
        "final": (episodes.with_columns(final_target_distance_m=pl.when(pl.col("episode") == 2).then(-1e-9)
                                        .otherwise(pl.col("final_target_distance_m"))),
                  "column final_target_distance_m holds -1e-09, not a possible value (the measure is >= 0; "
                  "graftcache.rollout.graded)"),
        "sunk": (episodes.with_columns(target_lift_m=pl.lit(-0.01)),
                 "column target_lift_m holds -0.01, not a possible value (the measure is >= 0; "
                 "graftcache.rollout.graded)"),
        "goal": (episodes.with_columns(goal_fraction=pl.lit(7.0)),
                 "column goal_fraction holds 7.0, not a possible value (the measure is in [0, 1]; "
                 "graftcache.rollout.graded)"),
    }
    for name, (frame, line) in cases.items():
        frame.write_parquet(tmp_path / f"{name}.parquet")
        with pytest.raises(GraftcacheError) as refused:
            A.read_rollouts(tmp_path / f"{name}.parquet", results)
        assert str(refused.value) == f"{tmp_path / name}.parquet: {line}", name
    bounds = episodes.with_columns(goal_fraction=pl.lit(1.0), target_lift_m=pl.lit(0.0), min_target_distance_m=0.0)
    bounds.write_parquet(tmp_path / "bounds.parquet")
    assert A.read_rollouts(tmp_path / "bounds.parquet", results)["goal_fraction"].to_list() == [1.0] * 24
    episodes.with_columns(pl.col("grasped").cast(pl.Int8)).write_parquet(tmp_path / "ones.parquet")
    assert A.read_rollouts(tmp_path / "ones.parquet", results)["grasped"].to_list() == episodes["grasped"].to_list()


def test_a_repeated_episode_is_refused_naming_it_and_its_copies(tmp_path: Path) -> None:
    """The same episode appended twice (3 episodes would count as 5) is refused, by episode_id where the file has
    it, else by run_id and the pair key; a table without a key has nothing to tell repeats by and reads."""
    results = _results()
    episodes = _episodes(results)
    ids = episodes.with_columns(episode_id=pl.format("e{}-{}", pl.col("run_id").str.slice(0, 4), pl.col("episode")))
    repeated = pl.concat([ids, ids[2:3], ids[2:3], ids[7:8]])
    repeated.write_parquet(tmp_path / "ids.parquet")
    with pytest.raises(GraftcacheError) as refused:
        A.read_rollouts(tmp_path / "ids.parquet", results)
    assert str(refused.value) == (f"{tmp_path / 'ids.parquet'}: episode episode_id={ids['episode_id'][2]} appears 3 "
                                  "times (and 1 more repeated episode(s)): each episode must be one row; keep one "
                                  "copy of each")
    keyed = pl.concat([episodes, episodes[5:6]]).with_columns(pl.lit(None, pl.Float64).alias("perturbation_m"))
    keyed.write_parquet(tmp_path / "keyed.parquet")
    with pytest.raises(GraftcacheError) as refused:
        A.read_rollouts(tmp_path / "keyed.parquet", results)
    assert str(refused.value) == (f"{tmp_path / 'keyed.parquet'}: episode run_id={episodes['run_id'][5]}, "
                                  "suite=libero_object, task_index=0, episode=1, seed=1001, max_steps=60, "
                                  "perturbation_m=0.0 appears 2 times: each episode must be one row; keep one copy "
                                  "of each")
    other_seed = pl.concat([episodes, episodes[5:6].with_columns(seed=pl.lit(7, pl.Int64))])
    other_seed.write_parquet(tmp_path / "seed.parquet")
    assert len(A.read_rollouts(tmp_path / "seed.parquet", results)) == 25
    bare = pl.concat([episodes, episodes[5:6]]).select("run_id", "success")
    bare.write_parquet(tmp_path / "bare.parquet")
    assert len(A.read_rollouts(tmp_path / "bare.parquet", results)) == 25
