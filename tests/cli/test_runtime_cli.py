"""Machine-independent defaults and honest command lines: compute dtype `auto`, seed syntax, value
ranges, progress output off a terminal, train-tiny at any step count."""

from __future__ import annotations

import argparse
import io
from pathlib import Path

import pytest
import torch
from helpers.probes import run_cli

from graftcache import runtime
from graftcache.cli import build_parser
from graftcache.codecs import int_list, seeds_value
from graftcache.errors import GraftcacheError
from graftcache.pretrain import TinyTrainConfig, warmup_cosine
from graftcache.progress import LogProgress, progress

SAMPLE = Path(__file__).resolve().parents[2] / "data" / "libero_sample"


@pytest.mark.parametrize(("avx512_bf16", "amx", "want"), [(False, False, "fp32"), (True, False, "bf16"),
                                                          (False, True, "bf16")])
def test_auto_compute_dtype_follows_the_cpu(monkeypatch, avx512_bf16: bool, amx: bool, want: str) -> None:
    monkeypatch.delenv(runtime.CPU_BF16_ENV, raising=False)
    monkeypatch.setattr(torch.cpu, "_is_avx512_bf16_supported", lambda: avx512_bf16)
    monkeypatch.setattr(torch.cpu, "_is_amx_tile_supported", lambda: amx)
    assert runtime.resolve_compute_dtype("auto", "cpu") == want
    assert runtime.resolve_compute_dtype("fp32", "cpu") == "fp32"  # explicit choices are kept
    assert runtime.resolve_compute_dtype("bf16", "cpu") == "bf16"


@pytest.mark.parametrize(("forced", "want"), [("0", "fp32"), ("1", "bf16")])
def test_the_other_cpu_family_is_reproduced_by_the_environment(monkeypatch, forced: str, want: str) -> None:
    """$GRAFTCACHE_CPU_BF16 wins over what torch reports either way, so one machine runs both `auto` paths."""
    monkeypatch.setattr(torch.cpu, "_is_avx512_bf16_supported", lambda: forced == "0")
    monkeypatch.setattr(torch.cpu, "_is_amx_tile_supported", lambda: False)
    monkeypatch.setenv(runtime.CPU_BF16_ENV, forced)
    assert runtime.resolve_compute_dtype("auto", "cpu") == want
    monkeypatch.setenv(runtime.CPU_BF16_ENV, "yes")
    with pytest.raises(GraftcacheError, match=r"\$GRAFTCACHE_CPU_BF16='yes': expected 1 \(bf16 in hardware\), 0"):
        runtime.resolve_compute_dtype("auto", "cpu")
    monkeypatch.setenv(runtime.CPU_BF16_ENV, "")  # empty: ask torch
    assert runtime.resolve_compute_dtype("auto", "cpu") == ("fp32" if forced == "1" else "bf16")


@pytest.mark.parametrize(("bf16", "want"), [(True, "bf16"), (False, "fp32")])
def test_auto_compute_dtype_on_cuda(monkeypatch, bf16: bool, want: str) -> None:
    monkeypatch.setitem(runtime.HARDWARE_BF16, "cuda", lambda _dev: bf16)
    assert runtime.resolve_compute_dtype("auto", torch.device("cuda", 0)) == want


def test_compute_dtype_errors_are_one_line() -> None:
    with pytest.raises(GraftcacheError, match="compute dtype 'fp8'"):
        runtime.resolve_compute_dtype("fp8", "cpu")
    with pytest.raises(GraftcacheError, match="--device 'foo': expected cpu, cuda or cuda:N"):
        runtime.resolve_device("foo")


def test_seed_syntax() -> None:
    assert seeds_value("3") == (0, 1, 2)
    assert seeds_value("0,2") == (0, 2) and seeds_value("0-2") == (0, 1, 2)
    with pytest.raises(argparse.ArgumentTypeError, match="use --seed 0"):
        seeds_value("0")
    assert int_list("0") == (0,) and int_list("0-3,7") == (0, 1, 2, 3, 7)
    for bad in ("-1", "x", "3-1", ",", "0,0", "0-3,2"):
        with pytest.raises(argparse.ArgumentTypeError):
            int_list(bad)
    fit = ["fit", "--backbone", "smolvla", "--encoder", "e", "--suite", "libero_spatial"]
    assert build_parser().parse_args(fit).seeds == (0, 1, 2)
    assert build_parser().parse_args([*fit, "--seed", "0"]).seeds == (0,)
    assert build_parser().parse_args([*fit, "--seeds", "0,2"]).seeds == (0, 2)


@pytest.mark.parametrize("args", [
    ["fit", "--backbone", "smolvla", "--encoder", "e", "--suite", "libero_spatial", "--seeds", "0"],
    ["fit", "--backbone", "smolvla", "--encoder", "e", "--suite", "libero_spatial", "--seeds", "-1"],
    ["fit", "--backbone", "smolvla", "--encoder", "e", "--suite", "libero_spatial", "--seed", "0", "--seeds", "2"],
    ["extract", "--encoder", "mobilenetv2", "--dataset", "d", "--batch-size", "0"],
    ["extract", "--encoder", "mobilenetv2", "--dataset", "d", "--block-frames", "0"],
    ["extract", "--encoder", "mobilenetv2", "--dataset", "d", "--episodes", "-1"],
    ["extract", "--encoder", "mobilenetv2", "--dataset", str(SAMPLE), "--device", "foo"],
    ["train-tiny", "--backbone", "smolvla", "--steps", "0"],
])
def test_bad_values_are_one_line_errors_before_any_work(args: list[str], capsys) -> None:
    done = run_cli(args, capsys)  # in this process: an exception escaping main() fails the test as a traceback would
    assert done.code == 2, done.err
    assert done.last.startswith(("graftcache", "usage")) and done.out == ""


def test_requests_check_their_ranges() -> None:
    from graftcache.extract import ExtractRequest
    from graftcache.fit.run import FitRequest

    with pytest.raises(GraftcacheError, match="seeds = \\(\\) must list at least one seed"):
        FitRequest(backbone="smolvla", encoder="e", suite="libero_spatial", seeds=())
    with pytest.raises(GraftcacheError, match="batch_size = 0 must be > 0"):
        ExtractRequest(dataset="d", encoder="e", batch_size=0)
    with pytest.raises(GraftcacheError, match="steps = 0 must be > 0"):
        TinyTrainConfig(steps=0)


def test_log_progress_prints_about_every_tenth(capsys) -> None:
    stream = io.StringIO()
    bar = LogProgress(total=1000, desc="extract k", unit="frame", stream=stream)
    for _ in range(1000):
        bar.update(1)
    bar.close()
    lines = stream.getvalue().splitlines()
    assert 9 <= len(lines) <= 11  # 10%, 20%, ..., 90% and the final line; no carriage returns
    assert "\r" not in stream.getvalue() and lines[0].startswith("extract k:  10% 100/1000 frame")
    assert "frame/s" in lines[0] and "eta" in lines[0] and lines[-1].startswith("extract k: 100% 1000/1000")
    assert isinstance(progress(range(3), desc="x"), LogProgress)  # pytest's stderr is not a terminal


@pytest.mark.parametrize("steps", [1, 2, 5, 10, 20, 30, 300])
def test_lr_schedule_is_defined_for_every_step_count(steps: int) -> None:
    factors = [warmup_cosine(steps, 0.1)(i) for i in range(steps)]
    assert all(0.0 <= f <= 1.0 for f in factors) and max(factors) == 1.0
    ramp = max(1, round(0.1 * steps))
    assert factors[ramp - 1] == 1.0 and factors == sorted(factors[:ramp]) + factors[ramp:]


def test_train_tiny_runs_ten_steps(tmp_path: Path, capsys) -> None:
    done = run_cli(["train-tiny", "--backbone", "smolvla", "--dataset", str(SAMPLE), "--steps", "10",
                    "--out", str(tmp_path / "p"), "--cache", str(tmp_path / "c")], capsys)
    assert done.code == 0, done.err[-2000:]
    assert (tmp_path / "p" / "model.safetensors").is_file()
    record = (tmp_path / "p" / "graftcache_pretrain.json").read_text()
    assert '"steps": 10' in record and '"compute_dtype": "' + runtime.resolve_compute_dtype("auto", "cpu") in record
    assert len(done.err.splitlines()) < 40  # sparse log lines, not a redraw per step


def test_train_tiny_saves_no_checkpoint_that_training_broke(v2_pi, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                           capsys: pytest.CaptureFixture) -> None:
    """A run whose weights end NaN (an lr or weight decay its steps diverge under, within their ranges) is refused
    in one line with nothing saved: saved, `--policy tiny` would find it again and graft onto it."""
    from graftcache import pretrain
    from graftcache.cli import main

    def diverging(adapter, *args, **kwargs) -> list[float]:
        losses = real(adapter, *args, **kwargs)
        next(adapter.policy.parameters()).data.fill_(float("nan"))
        return losses

    real = pretrain.optimise
    monkeypatch.setattr(pretrain, "optimise", diverging)
    out = tmp_path / "policy"
    assert main(["train-tiny", "--backbone", "smolvla", "--dataset", str(v2_pi.root), "--steps", "1",
                 "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()  # decoding's progress lines, then the one error line
    assert "Traceback" not in "".join(err)
    assert "train-tiny smolvla: training diverged (its weights hold NaN/inf after 1 step(s), lr 0.001" in err[-1]
    assert "nothing saved" in err[-1] and not (out / "config.json").exists()
