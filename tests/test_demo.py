"""`graftcache demo` end to end, as the README runs it: offline, fresh cache root, real bundled sample.
Then a rerun that reuses every cache and cell, and the analysis notebook executed on the demo's results."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import polars as pl
import pytest
from helpers.notebook import execute_notebook

from graftcache import results
from graftcache.store import list_caches

GRAFTCACHE = Path(sys.executable).with_name("graftcache")


def _demo(home: Path, cwd: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "GRAFTCACHE_HOME": str(home), "HF_HUB_OFFLINE": "1", "PYTHONUNBUFFERED": "1"}
    run = subprocess.run([str(GRAFTCACHE), "demo"], cwd=cwd, env=env, capture_output=True, text=True, timeout=2400)
    assert run.returncode == 0, run.stderr[-4000:]
    return run


@pytest.mark.slow
def test_demo_runs_offline_reuses_everything_and_feeds_the_notebook(tmp_path: Path,
                                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    home = tmp_path / "home"
    first = _demo(home, tmp_path)
    table = results.read(home / "demo" / "results.parquet")
    # per (backbone, suite, seed): 3 encoders x (plain, zero-image, shuffled-image) + native + native-graft
    assert table.height == 2 * 2 * 2 * (3 * 3 + 2) == 88
    assert set(table["backbone"]) == {"smolvla", "pi05"}
    assert set(table["suite"]) == {"libero_spatial", "libero_object"}
    assert {"mobilenetv2", "efficientnet-lite0", "smolvla-native", "pi05-native"} <= set(table["encoder"])
    assert table["eval_mse"].is_finite().all() and (table["n_eval_frames"] > 0).all()
    assert table["random_init"].all()  # tiny backbones are never released weights
    assert table["backbone_random_init"].all()
    real = pl.col("encoder").is_in(["mobilenetv2", "efficientnet-lite0"])
    assert not table.filter(real)["encoder_random_init"].any() and table.filter(~real)["encoder_random_init"].all()
    _assert_findings(table)
    report = home / "demo" / "report"
    md = (report / "report.md").read_text()
    assert "random-init" in md.lower() and "proxy" in md.lower()
    assert sorted(p.suffix for p in report.glob("*.png")) and (report / "report.html").is_file()
    assert f"report: {report / 'report.md'}" in first.stdout
    caches = {c.key for c in list_caches(home)}
    assert len(caches) == 5  # three encoders + two native towers, all complete

    again = _demo(home, tmp_path)
    log = again.stdout + again.stderr
    assert "wrote " not in log and "training tiny" not in log
    assert "loading backbone" not in log  # a finished sweep loads no policy at all
    assert first.stdout.count("loading backbone") == 2  # one load per backbone for all 120 cells
    assert log.count("skip ") == 12  # one line per request: backbone x encoder x suite
    assert {c.key for c in list_caches(home)} == caches
    rerun = results.read(home / "demo" / "results.parquet")
    assert rerun.sort("run_id").select("run_id", "eval_mse").equals(table.sort("run_id").select("run_id", "eval_mse"))

    run = execute_notebook(home / "demo" / "results.parquet", tmp_path, monkeypatch)
    assert not run.errors
    # the ladder is ordered by the parameters each row records: the tiny pi0.5 (~1.3M) is smaller than the
    # tiny SmolVLA (~3.5M), unlike the released policies
    sizes = dict(table.group_by("backbone").agg(pl.col("backbone_params").unique()).iter_rows())
    assert all(len(v) == 1 for v in sizes.values())
    order = sorted(sizes, key=lambda b: sizes[b][0])
    assert f"88 rows; backbones {order}; " in run.text
    assert run.figures == 3
    native = table.filter(pl.col("control") == "native").group_by("backbone").agg(pl.col("eval_mse").mean())
    zero = table.filter(pl.col("control") == "zero-image").group_by("backbone").agg(pl.col("eval_mse").mean())
    joined = native.join(zero, on="backbone", suffix="_zero")
    assert (joined["eval_mse"] < joined["eval_mse_zero"]).all()  # the tiny backbones use vision


def _seeds(table: pl.DataFrame, **match: str) -> pl.Series:
    rows = table.filter(*(pl.col(k) == v for k, v in match.items()))
    assert rows.height, match
    return rows["eval_mse"]


def _assert_findings(table: pl.DataFrame) -> None:
    """The two findings the demo's report exists to show, each on every seed (the worst seed of the better side
    below the best seed of the worse one): every tiny backbone reads its cameras (its own tower beats zero-image on
    both suites), and on every backbone an encoder with real ImageNet weights beats its own zero-image and
    shuffled-image controls on at least one suite."""
    real = {"mobilenetv2", "efficientnet-lite0"}
    for backbone in ("smolvla", "pi05"):
        for suite in ("libero_spatial", "libero_object"):
            native = _seeds(table, backbone=backbone, suite=suite, control="native")
            zero = _seeds(table, backbone=backbone, suite=suite, control="zero-image")
            assert native.max() < zero.min(), (backbone, suite, native.to_list(), zero.sort().to_list())
        wins = [
            (encoder, suite) for encoder in real for suite in ("libero_spatial", "libero_object")
            if _seeds(table, backbone=backbone, suite=suite, encoder=encoder, control="none").max()
            < min(_seeds(table, backbone=backbone, suite=suite, encoder=encoder, control=c).min()
                  for c in ("zero-image", "shuffled-image"))
        ]
        assert wins, f"{backbone}: no real-weights encoder beats its zero-image and shuffled-image controls"
