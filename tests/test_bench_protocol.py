"""benchmarks/bench_protocol.py at tiny settings on the tiny backbones: the CPU smoke test of the protocol
benchmark. Its JSON must add up: projected hours are loads + training + evaluation, the online protocol costs
at least the cached one, and the FLOP bounds follow from the counted FLOPs and the named peak."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

from devtools.libero_counts import LIBERO_COUNTS

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


@pytest.mark.slow
def test_bench_protocol_runs_and_its_json_adds_up(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                   capsys: pytest.CaptureFixture) -> None:
    monkeypatch.syspath_prepend(str(BENCHMARKS))
    monkeypatch.delitem(sys.modules, "bench_protocol", raising=False)
    import bench_protocol

    out = tmp_path / "protocol.json"
    report = bench_protocol.main(["--tiny", "--device", "cpu", "--compute-dtype", "fp32", "--steps", "1",
                                  "--eval-frames", "1", "--batch-size", "1", "--encoders", "dinov2-s",
                                  "--out", str(out)])
    assert json.loads(out.read_text()) == report
    assert report["device"] == "cpu" and "cores" in report["cpu"] and report["tiny"] is True
    # cli/paper.toml: 2 backbones x 2 suites x 3 seeds x (1 encoder x 6 encoder-reading kinds of row + 2 native)
    assert report["rows"] == 2 * 2 * 3 * (1 + 5 + 2)
    assert report["settings"]["steps"] == 2000 and report["settings"]["num_denoise_steps"] == 10
    assert report["held_out_frames"] == {s: round(LIBERO_COUNTS[s][1] * 0.2) for s in ("libero_spatial",
                                                                                       "libero_object")}
    parts = report["loads_h"] + report["training_h"] + report["evaluation_h"]
    assert report["projected_h"] == pytest.approx(parts, rel=1e-12)
    assert all(report[k] > 0 for k in ("loads_h", "training_h", "evaluation_h", "extraction_h", "flops"))
    assert report["online_h"] > report["projected_h"]
    assert report["flop_bound_h_40"] == pytest.approx(report["flop_bound_h_100"] / 0.4, rel=1e-12)
    assert report["flop_bound_h_100"] == pytest.approx(report["flops"] / report["peak_flops"] / 3600, rel=1e-12)
    assert report["peak_source"].startswith("measured: 2048^3 matmul")
    kinds = report["kinds"]
    assert {k["backbone"] for k in kinds} == {"smolvla", "pi05"}
    trained = [k for k in kinds if k["train"]]
    assert trained and all(k["step_s"] > 0 and k["step_flops"] > 0 for k in trained)
    assert all(k["activation_checkpointing"] == "off" for k in trained)  # auto, on a CPU step that fits
    assert any(k["lora"] for k in trained) and any(not k["train"] for k in kinds)
    assert all(k["eval_s_per_frame"] > 0 and k["eval_flops_per_frame"] > 0 for k in kinds)
    # a pool-16x16 kind reads 256 tokens a camera; the LoRA kind costs more FLOPs than the plain graft's
    assert any(k["tokens"] == 256 for k in trained)
    plain = {(k["backbone"], k["width"]): k for k in trained if not k["lora"] and k["tokens"] != 256}
    for k in trained:
        if k["lora"]:
            assert k["step_flops"] > plain[k["backbone"], k["width"]]["step_flops"]
    assert "device-hours" in capsys.readouterr().out
