"""The report's closed-loop section, figure and closed_loop.csv with graded rollouts (issue 43, item 4).

smolvla on two suites, each with a native tower (rows for 2 seeds, as a sweep writes them, that are one policy:
graftcache.analysis.policies), two plain grafts (2 seeds each) and a zero-image row (1 seed), 3 episodes per row on
the same keys; the closest approach grows with eval_mse except that siglip seed 1 and dinov2-s seed 0 swap on
libero_spatial (GRAFTS below); every native episode comes 0.2 m closer than zero-image's.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import polars as pl
import pytest
from helpers.tables import row, table

from graftcache import analysis as A
from graftcache import report
from graftcache import results as R
from graftcache.report.closed_loop_figure import figure_closed_loop

# (encoder, seed, control) -> (eval_mse, mean closest approach per suite)
GRAFTS = {
    ("smolvla-native", 0, "native"): (0.80, {"libero_object": 0.06, "libero_spatial": 0.07}),
    ("smolvla-native", 1, "native"): (0.80, {"libero_object": 0.06, "libero_spatial": 0.07}),  # the same policy
    ("siglip", 0, "none"): (0.90, {"libero_object": 0.10, "libero_spatial": 0.10}),
    ("siglip", 1, "none"): (0.95, {"libero_object": 0.12, "libero_spatial": 0.16}),
    ("dinov2-s", 0, "none"): (1.00, {"libero_object": 0.15, "libero_spatial": 0.13}),
    ("dinov2-s", 1, "none"): (1.10, {"libero_object": 0.18, "libero_spatial": 0.19}),
    ("siglip", 0, "zero-image"): (1.40, {"libero_object": 0.27, "libero_spatial": 0.27}),
}
OFFSETS = (-0.01, 0.0, 0.01)  # the three episodes around each cell's mean


def _files(tmp_path: Path, graded_for: int = 3) -> tuple[Path, Path]:
    """results and rollouts; only the first `graded_for` episodes of each cell carry graded columns."""
    rows = [row("smolvla", suite, e, s, mse, control=c) for suite in ("libero_object", "libero_spatial")
            for (e, s, c), (mse, _) in GRAFTS.items()]
    episodes = []
    for r in rows:
        near = GRAFTS[r["encoder"], r["seed"], r["control"]][1][r["suite"]]
        for k, offset in enumerate(OFFSETS):
            graded = k < graded_for
            episodes.append({"run_id": r["run_id"], "suite": r["suite"], "task_index": 0, "episode": k,
                             "seed": 1000 + k, "max_steps": 60, "perturbation_m": 0.03 if graded else None,
                             "success": r["control"] == "native" and k == 0,
                             "min_target_distance_m": near + offset if graded else None,
                             "grasped": (near < 0.1) if graded else None})
    table(rows).write_parquet(tmp_path / "results.parquet")
    pl.DataFrame(episodes).write_parquet(tmp_path / "rollouts.parquet")
    return tmp_path / "results.parquet", tmp_path / "rollouts.parquet"


def _analysed(results: Path, rollouts: Path) -> A.Analysis:
    """The analysis of the files read as the report reads them (each row's policy_id filled from its cell)."""
    table = R.read_for_report(results)
    return A.analyze(table, rollouts=A.read_rollouts(rollouts, table))


@pytest.fixture
def written(tmp_path: Path) -> tuple[report.ReportPaths, A.Analysis]:
    results, rollouts = _files(tmp_path)
    return report.write_report(results, tmp_path / "out", rollouts=rollouts), _analysed(results, rollouts)


def _head(a: A.Analysis, cells_of: str, suite: str = "libero_spatial") -> dict:
    return a.closed_loop.agreement.filter(pl.col("cells_of") == cells_of, pl.col("score") == "eval_mse",
                                          pl.col("measure") == "min_target_distance_m",
                                          pl.col("suite") == suite).row(0, named=True)


def test_the_section_prints_the_headline_agreement_with_its_intervals(written: tuple) -> None:
    paths, a = written
    md = paths.markdown.read_text()
    head = _head(a, "with controls")
    assert head["spearman"] == pytest.approx(1 - 6 * 2 / (6 * 35))  # one adjacent swap among 6 policies
    line = (f"SmolVLA · libero_spatial · with controls: Spearman ρ = {head['spearman']:+.2f} "
            f"[{head['spearman_low']:+.2f}, {head['spearman_high']:+.2f}], Kendall τb = {head['kendall_tau_b']:+.2f} "
            f"[{head['kendall_tau_b_low']:+.2f}, {head['kendall_tau_b_high']:+.2f}], MMRV = {head['mmrv']:.3g} m "
            f"[{head['mmrv_low']:.3g}, {head['mmrv_high']:.3g}] over 6 cells (3 episodes each).")
    assert line in md
    assert "The graded measures are unavailable" not in md


def test_the_candidates_lead_then_controls_then_the_pairwise_verdicts(written: tuple) -> None:
    """libero_spatial's four grafts: closest approach .10 .16 .13 .19 at eval_mse .90 .95 1.00 1.10 (one swap):
    rho = 1 - 6 * 2 / (4 * 15) = 0.8 over the candidates."""
    paths, a = written
    md = paths.markdown.read_text()
    head = _head(a, "candidates")
    assert head["cells"] == 4 and head["spearman"] == pytest.approx(0.8)
    assert f"SmolVLA · libero_spatial · candidates: Spearman ρ = +0.80 [{head['spearman_low']:+.2f}, " in md
    order = ["### Candidates: does `eval_mse` order the encoders", "### With controls: does looking help?",
             "### Which encoder wins? Pairwise verdicts", "### Native tower vs zero-image on the same episodes",
             "### Every score against every measure"]
    assert [md.index(h) for h in order] == sorted(md.index(h) for h in order)
    # dinov2-s - siglip: offline +.10 and +.15 on the 2 seeds (t interval with 1 df holds 0); closed loop +.03 m on
    # every one of the 6 (seed, key) pairs: siglip closer
    assert ("SmolVLA · libero_spatial: 0 of 0 pairs resolved by both agree (1 pair of candidate encoders: 0 offline "
            "only, 1 closed loop only, 0 neither).") in md
    assert "| SmolVLA | libero_spatial | dinov2-s | siglip | 2 | +0.125 [" in md and "| closed loop only |" in md


def test_the_findings_a_command_prints_are_the_candidates_then_each_pair(written: tuple) -> None:
    """ReportPaths.findings (what `demo --closed-loop` and `report --rollouts` print): per suite the candidates'
    agreement line as the report writes it, then the pairwise summary and each pair's line, its offline interval the
    paired t interval of the two seeds' differences (scipy), its closed-loop one +0.03 m on every pair; no dose rows,
    no resolution line."""
    from scipy import stats

    paths, a = written
    md = paths.markdown.read_text()
    heads = [line for line in paths.findings if " · candidates: " in line]
    assert len(heads) == 2 and all(f"- {h}" in md for h in heads) and paths.findings[0] == heads[0]
    offline = np.array([1.00 - 0.90, 1.10 - 0.95])
    low, high = stats.t.interval(0.95, 1, loc=offline.mean(), scale=stats.sem(offline))
    pair = (f"SmolVLA · libero_spatial · dinov2-s − siglip: offline {offline.mean():+.3g} [{low:+.3g}, {high:+.3g}] "
            f"over 2 seeds (not resolved), closed loop +0.03 m [+0.03, +0.03] over 6 pairs (better: "
            f"siglip): closed loop only.")
    summary = ("SmolVLA · libero_spatial: 0 of 0 pairs resolved by both agree (1 pair of candidate encoders: 0 "
               "offline only, 1 closed loop only, 0 neither).")
    assert paths.findings[-2:] == (summary, pair)
    assert len(paths.findings) == 2 + 2 * 2 and not any("resolution" in line for line in paths.findings)


def test_pairwise_csv_holds_the_verdicts_typed(written: tuple) -> None:
    paths, a = written
    csv = pl.read_csv(paths.pairwise, schema=report.PAIRWISE_CSV_SCHEMA)
    assert csv.equals(a.closed_loop.pairwise) and csv.height == 2 * len(A.MEASURES)
    near = csv.filter(pl.col("measure") == "min_target_distance_m", pl.col("suite") == "libero_spatial").row(
        0, named=True)
    assert (near["encoder_a"], near["encoder_b"], near["seeds"], near["pairs"]) == ("dinov2-s", "siglip", 2, 6)
    assert (near["offline"], near["closed"], near["verdict"]) == ("not resolved", "b", "closed loop only")


def test_the_section_prints_the_paired_control_line(written: tuple) -> None:
    paths, a = written
    md = paths.markdown.read_text()
    # the native policy's .07 (libero_spatial) against zero-image .27 on each of the 3 keys: -0.2 m; its two rows
    # are one policy, so one native cell and one seed
    assert ("SmolVLA · libero_spatial · closest approach: native tower 0.07 m vs zero-image 0.27 m on 3 paired "
            "episodes (1 native, 1 zero-image cells): native − zero-image = -0.2 m [-0.2, -0.2]: the native "
            "tower is better (lower is better); the native tower is better on 1 of 1 native seeds.") in md
    assert "| SmolVLA | libero_object | grasped | 1 | 1 | 3 |" in md  # every recorded measure in the table


def test_closed_loop_csv_holds_the_agreement_typed(written: tuple) -> None:
    paths, a = written
    csv = pl.read_csv(paths.closed_loop, schema=report.CLOSED_LOOP_CSV_SCHEMA)
    want = a.closed_loop.agreement.select(report.CLOSED_LOOP_CSV_COLUMNS)
    assert csv.height == 2 * 2 * 4 * 6 and csv.equals(want)
    near = csv.filter(pl.col("measure") == "min_target_distance_m", pl.col("score") == "eval_mse")
    assert near["cells_of"].to_list() == ["candidates", "with controls"] * 2
    assert near["cells"].to_list() == [4, 6, 4, 6] and min(near["replicates"]) > 950


def test_the_figure_draws_both_measures_per_suite_with_controls_marked(written: tuple) -> None:
    paths, a = written
    assert (paths.markdown.parent / "closed_loop.png").stat().st_size > 0
    fig = figure_closed_loop(a)
    axes = [ax for ax in fig.axes if ax.get_visible()]
    assert len(axes) == 6  # (closest approach with controls, over the candidates, success) x 2 suites
    near, zoomed, success = axes[3:]  # libero_spatial
    low, high = near.get_ylim()
    assert low > high  # distance axis inverted: up is closer
    assert high < 0.05 and low > 0.28  # fitted to the cells (0.07 .. 0.27), not from 0
    head = _head(a, "with controls")
    assert f"ρ {head['spearman']:+.2f} [{head['spearman_low']:+.2f}, {head['spearman_high']:+.2f}]" in near.get_title()
    markers = {line.get_marker() for line in near.get_lines()}
    assert {"*", "X", "o"} <= markers  # native, zero-image, grafts
    star = [line for line in near.get_lines() if line.get_marker() == "*"]
    assert [float(line.get_ydata()[0]) for line in star] == pytest.approx([0.07])  # one native policy
    assert any("native − zero-image: -0.2 m [-0.2, -0.2] over 3 paired episodes" in t.get_text()
               for t in near.texts)
    assert success.get_ylim() == pytest.approx((-0.05, 1.05))
    low, high = zoomed.get_ylim()
    assert 0.19 < low < 0.21 and 0.08 < high < 0.10  # fitted to the grafts (0.10 .. 0.19), controls left out
    assert {line.get_marker() for line in zoomed.get_lines()} == {"o"}
    assert zoomed.get_title().splitlines()[1].startswith("candidates (4): ρ +0.80")


def test_a_panel_that_can_only_say_undefined_is_dropped(tmp_path: Path) -> None:
    """Every episode failed: the success panels are gone, the distance panels stay."""
    results, rollouts = _files(tmp_path)
    pl.read_parquet(rollouts).with_columns(success=pl.lit(False)).write_parquet(rollouts)
    a = _analysed(results, rollouts)
    axes = [ax for ax in figure_closed_loop(a).axes if ax.get_visible()]
    assert len(axes) == 4 and not any("success" in ax.get_ylabel() for ax in axes)


def test_a_row_without_rolled_out_candidates_has_a_blank_candidates_panel(tmp_path: Path) -> None:
    """libero_spatial's plain grafts not rolled out (only its native and zero-image cells): its candidates panel is
    off, saying so, instead of an empty frame saying the graded measures are unavailable (they are recorded);
    libero_object's three panels are drawn."""
    results, rollouts = _files(tmp_path)
    table = R.read_for_report(results)
    plain = table.filter(pl.col("suite") == "libero_spatial", pl.col("control") == "none")["run_id"]
    pl.read_parquet(rollouts).filter(~pl.col("run_id").is_in(plain.implode())).write_parquet(rollouts)
    fig = figure_closed_loop(_analysed(results, rollouts))
    blank = [ax for ax in fig.axes if not ax.axison and ax.texts]
    said = [t.get_text() for ax in blank for t in ax.texts]
    assert said == ["SmolVLA · libero_spatial\nno candidates cell rolled out"]
    drawn = [ax for ax in fig.axes if ax.axison]
    assert len(drawn) == 5 and not any("unavailable" in t.get_text() for ax in fig.axes for t in ax.texts)


def test_a_partly_graded_file_says_how_many_episodes_lack_the_graded_measures(tmp_path: Path) -> None:
    results, rollouts = _files(tmp_path, graded_for=2)
    paths = report.write_report(results, tmp_path / "out", rollouts=rollouts)
    md = paths.markdown.read_text()
    # 6 policies (the native tower's two rows are one) x 2 suites x 3 episodes, the third of each ungraded
    assert ("The graded measures are unavailable for 12 of 36 episodes (format-1 rollouts rows, or a table without "
            "the graded columns)") in md
    a = _analysed(results, rollouts)
    cells = a.closed_loop.cells.filter(pl.col("control") == "zero-image")
    assert cells["graded_episodes"].to_list() == [2, 2] and cells["episodes"].to_list() == [3, 3]
    assert cells["min_target_distance_m"].to_list() == pytest.approx([np.mean([0.26, 0.27])] * 2)


def test_episodes_on_other_kernels_are_said_with_their_counts(tmp_path: Path) -> None:
    """A file whose episodes record two sets of kernels (one suite's first episodes run with `rollout --device cuda`)
    gets one paragraph counting the episodes on each, most first; a file without the column, or with one set of
    kernels, gets none."""
    results, rollouts = _files(tmp_path)
    sentence = "These episodes' policies computed on"
    assert sentence not in report.write_report(results, tmp_path / "none", rollouts=rollouts).markdown.read_text()
    table = pl.read_parquet(rollouts)
    cuda = (pl.col("suite") == "libero_spatial") & (pl.col("episode") == 0)
    table.with_columns(kernels=pl.when(cuda).then(pl.lit("cuda:sm_90")).otherwise(pl.lit("cpu:avx2"))).write_parquet(
        rollouts)
    a = _analysed(results, rollouts)
    assert a.closed_loop.kernels == {"cpu:avx2": 30, "cuda:sm_90": 6}  # 6 policies x 2 suites x 3 episodes
    md = report.write_report(results, tmp_path / "mixed", rollouts=rollouts).markdown.read_text()
    assert (f"{sentence} 2 sets of kernels (episodes: cpu:avx2: 30, cuda:sm_90: 6; the rollouts column "
            "`kernels`).") in md
    table.with_columns(kernels=pl.lit("cpu:avx2")).write_parquet(rollouts)
    assert sentence not in report.write_report(results, tmp_path / "one", rollouts=rollouts).markdown.read_text()
    table.with_columns(kernels=pl.when(cuda).then(pl.lit("cuda:sm_90"))).write_parquet(rollouts)
    md = report.write_report(results, tmp_path / "unrecorded", rollouts=rollouts).markdown.read_text()
    assert f"{sentence} 2 sets of kernels (episodes: not recorded: 30, cuda:sm_90: 6;" in md
