"""benchmarks/gpu_check.py's closed-loop stage (11, benchmarks/gpu_closed_loop.py) in its CPU dry run: each arm is a
real `graftcache rollout --workers 2` in the LIBERO simulator, whose rows must be the episodes the in-process rollout of
the same cells gives (tests/fixtures/simulator_cells.py), and whose rates must be what its rows and wall time say; the
comparison of rows across kernels is checked on hand-made tables."""

from __future__ import annotations

import json
import statistics
import sys
from pathlib import Path

import polars as pl
import pytest
from fixtures.simulator_cells import Fitted, RolledOut

from graftcache.rollout import rollouts_file
from graftcache.runtime import kernels, resolve_device

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


def _module(monkeypatch: pytest.MonkeyPatch, name: str):  # noqa: ANN202
    monkeypatch.syspath_prepend(str(BENCHMARKS))
    monkeypatch.delitem(sys.modules, name, raising=False)
    return __import__(name)


@pytest.mark.slow
def test_the_closed_loop_stage_rolls_out_the_cells_on_each_path_and_compares_their_rows(
        simulator_cells: Fitted, simulator_rollouts: RolledOut, tmp_path: Path,
        monkeypatch: pytest.MonkeyPatch) -> None:
    gpu_check = _module(monkeypatch, "gpu_check")
    out = tmp_path / "check.json"
    data = gpu_check.main(["--tiny", "--device", "cpu", "--stages", "11", "--closed-loop-cells",
                           str(simulator_cells.results.parent), "--closed-loop-episodes", "2", "--closed-loop-steps",
                           "5", "--scratch", str(tmp_path / "scratch"), "--budget-s", "3600", "--out", str(out)])
    assert json.loads(out.read_text()) == json.loads(json.dumps(data, default=str)) and data["done"] is True
    stage = data["stages"]["11_closed_loop"]
    assert list(stage) == ["device_w2", "cpu_w2", "ratio_w2"]  # the device path first, then the CPU path's
    # the fixture's rows: the same 2 cells x 2 episodes of 5 steps, run in one process (with videos)
    expected = simulator_rollouts.rows.drop("seconds", "command", "kernels", "video")
    for name in ("device_w2", "cpu_w2"):
        entry = stage[name]
        assert entry["status"] == "ok", entry
        rows = rollouts_file.read(tmp_path / "scratch" / "closed-loop" / name / "rollouts.parquet")
        assert rows.drop("seconds", "command", "kernels", "video").sort("episode_id").equals(expected)
        assert rows["kernels"].unique().to_list() == entry["kernels"] == [kernels(resolve_device("cpu"))]
        assert (entry["policy_device"], entry["mujoco_gl"], entry["workers"], entry["episodes"]) == ("cpu", "egl", 2, 4)
        assert entry["episodes_per_hour"] == pytest.approx(4 / entry["wall_s"] * 3600, rel=0.02)
        median = statistics.median(rows["seconds"].to_list())
        assert entry["median_episode_s"] == pytest.approx(median, abs=1e-3)
        assert entry["steady_episodes_per_hour"] == pytest.approx(2 * 3600 / median, rel=1e-3)
        assert not entry["renderer"].startswith("unavailable"), entry["renderer"]
    rows = stage["cpu_w2"]["rows"]
    assert rows["equal"] is True and rows["within_tolerance"] is True and rows["against"] == "device_w2"
    assert rows["same_success_and_steps"] == rows["episodes"] == 4 and set(rows["max_drift_m"].values()) == {0.0}
    ratio = stage["ratio_w2"]
    assert ratio["episodes_per_hour"] == pytest.approx(
        stage["device_w2"]["episodes_per_hour"] / stage["cpu_w2"]["episodes_per_hour"], abs=0.01)


def _rows(distance: list[float], success: list[bool], kernel: str) -> pl.DataFrame:
    row = {c: None for c in rollouts_file.SCHEMA}
    return pl.DataFrame([{**row, "episode_id": f"{k:016x}", "format_version": 3, "success": s, "steps": 5,
                          "seconds": 1.0 + k, "kernels": kernel, "min_target_distance_m": d,
                          "final_target_distance_m": 0.3, "target_lift_m": 0.0}
                         for k, (d, s) in enumerate(zip(distance, success, strict=True))],
                        schema=rollouts_file.SCHEMA)


@pytest.mark.parametrize("distance, success, within, drift", [
    ([0.100, 0.200], [False, True], True, 0.0),       # equal apart from seconds and kernels
    ([0.1015, 0.200], [False, True], True, 0.0015),   # a drift inside TOLERANCE_M
    ([0.100, 0.2025], [False, True], False, 0.0025),  # past it
    ([0.100, 0.200], [True, True], False, 0.0),       # another outcome
])
def test_rows_on_other_kernels_compare_by_outcome_and_drift(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, distance: list[float], success: list[bool], within: bool,
        drift: float) -> None:
    closed_loop = _module(monkeypatch, "gpu_closed_loop")
    assert closed_loop.TOLERANCE_M == 0.002
    (tmp_path / "cpu").mkdir()
    (tmp_path / "gpu").mkdir()
    _rows([0.100, 0.200], [False, True], "cpu:avx2").write_parquet(tmp_path / "cpu" / "rollouts.parquet")
    _rows(distance, success, "cuda:sm_90").write_parquet(tmp_path / "gpu" / "rollouts.parquet")
    got = closed_loop.compared(tmp_path / "gpu" / "rollouts.parquet", tmp_path / "cpu" / "rollouts.parquet")
    assert got["against"] == "cpu" and got["episodes"] == 2 and got["within_tolerance"] is within
    assert got["equal"] is (within and drift == 0.0)
    assert got["max_drift_m"]["min_target_distance_m"] == pytest.approx(drift, abs=1e-12)
    assert got["same_success_and_steps"] == 2 - (success != [False, True])
    _rows([0.1], [False], "cuda:sm_90").write_parquet(tmp_path / "gpu" / "rollouts.parquet")
    with pytest.raises(RuntimeError, match="other episodes than"):
        closed_loop.compared(tmp_path / "gpu" / "rollouts.parquet", tmp_path / "cpu" / "rollouts.parquet")
