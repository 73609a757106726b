"""The report's dose-response section and figure on tests/helpers/dose_tables.py's hand table (its resolution 0.02),
with the table's plain rows of two more encoders so every other section has candidates to rank: the noise-A rows are
controls (the controls table lists them against their encoder), never candidate encoders."""

from __future__ import annotations

from pathlib import Path

import polars as pl
from helpers.dose_tables import dose_tables
from helpers.tables import row, table

from graftcache import analysis as A
from graftcache import report
from graftcache.report.dose_figure import figure_dose


def _files(tmp_path: Path) -> tuple[Path, Path]:
    results, episodes = dose_tables()
    more = [row("smolvla", "libero_object", e, s, 1.5 + s / 10) for e in ("resnet18",) for s in range(3)]
    table([*results.to_dicts(), *more]).write_parquet(tmp_path / "results.parquet")
    episodes.write_parquet(tmp_path / "rollouts.parquet")
    return tmp_path / "results.parquet", tmp_path / "rollouts.parquet"


def test_the_report_states_each_curve_and_its_resolution(tmp_path: Path) -> None:
    results, rollouts = _files(tmp_path)
    paths = report.write_report(results, tmp_path / "out", rollouts=rollouts)
    md = paths.markdown.read_text()
    assert ("SmolVLA / libero_object / siglip (5 doses): offline monotone within noise, closed loop monotone; "
            "resolution 0.02 eval_mse (the smallest offline gap between adjacent doses that the closed loop "
            "confirms).") in md
    # dinov2-s: only its stand-in blind cells (siglip's zero-image) were rolled out
    assert ("SmolVLA / libero_object / dinov2-s (3 doses): offline monotone, closed loop without a measured step; "
            "resolution undefined: no step confirmed by the closed loop at the 12 episodes spent.") in md
    # what a command prints ends with each curve's resolution line, as the report states it
    assert [line for line in paths.findings if "eval_mse (the smallest" in line or "resolution undefined" in line] \
        == list(paths.findings[-2:]) and all(f"- {line}" in md for line in paths.findings[-2:])
    # the step that sets the resolution: confirmed by 12 pairs, not resolved offline by 3 seeds
    assert ("| SmolVLA | libero_object | siglip | 0.25 → 0.5 | 0.02 [-0.004841, 0.04484] | 0.011 [0.010, 0.011] | no | "
            "12 | yes |") in md
    assert (paths.markdown.parent / "dose.png").stat().st_size > 0
    a = A.analyze(pl.read_parquet(results), rollouts=A.read_rollouts(rollouts, pl.read_parquet(results)))
    assert set(a.band["encoder"]) == {"siglip", "dinov2-s", "resnet18"}  # candidates: the plain grafts alone
    dosed = a.controls.filter(pl.col("control").str.starts_with("noise-"))
    assert set(zip(dosed["encoder"], dosed["control"], strict=True)) >= {
        ("siglip", "noise-0.25"), ("siglip", "noise-0.5"), ("siglip", "noise-0.75"), ("dinov2-s", "noise-0.5")}


def test_the_figure_draws_both_sides_with_intervals(tmp_path: Path) -> None:
    results, rollouts = _files(tmp_path)
    a = A.analyze(pl.read_parquet(results), rollouts=A.read_rollouts(rollouts, pl.read_parquet(results)))
    fig = figure_dose(a)
    offline, loop = fig.axes[0], fig.axes[1]  # the first curve: dinov2-s (curves are sorted by encoder)
    assert "dinov2-s" in offline.get_title() and "resolution —" in loop.get_title()
    assert not [line for line in loop.get_lines() if len(line.get_xdata()) == 2]  # one dose rolled out: no step
    offline, loop = fig.axes[2], fig.axes[3]  # siglip
    assert "resolution 0.02" in loop.get_title()
    styles = [line.get_linestyle() for line in loop.get_lines() if len(line.get_xdata()) == 2]
    assert styles == ["-", "-", "-", "--"]  # the last step is not confirmed
    low, high = offline.get_ylim()
    assert 0.8 < low < 0.98 and 1.45 < high < 1.7  # fitted to the intervals (0.93 .. 1.53), not from 0
    assert len(offline.collections) == len(loop.collections) == 1  # one errorbar set a side: the intervals
    assert figure_dose(A.analyze(pl.read_parquet(results).filter(~pl.col("control").str.starts_with("noise-")))) \
        is None


def test_without_dose_rows_there_is_no_section(tmp_path: Path) -> None:
    results, _ = _files(tmp_path)
    plain = pl.read_parquet(results).filter(~pl.col("control").str.starts_with("noise-"))
    md = report.write_report(plain, tmp_path / "out").markdown.read_text()
    assert "Dose response" not in md and not (tmp_path / "out" / "dose.png").exists()
