"""One home per setting: a request field's declaration (graftcache/requests.py) is its flag, its recipe key, its
range check and its text in recorded command lines. Checked through what users see: parsed flags, refused values,
command lines that parse back to the same request."""

from __future__ import annotations

import argparse
import shlex
from dataclasses import dataclass, fields

import pytest
from helpers.probes import run_cli

from graftcache.checks import POSITIVE
from graftcache.cli import build_parser
from graftcache.cli.common import add_flags, request_from
from graftcache.errors import GraftcacheError
from graftcache.recipe import SECTION_KEYS
from graftcache.requests import CONTROLS, EVAL_SPLITS, OBJECTIVES, ExecutorSettings, ExtractRequest, FitRequest
from graftcache.settings import Checked, declared, recipe_keys, renamed, setting
from graftcache.sweep import command_line

FIT = FitRequest(backbone="pi05", encoder="dinov2-s", suite="libero_goal", policy="/ckpt", dataset="/data",
                 cache_key="k1", native_cache_key="k2", camera_map="image=agentview,image2=wrist", seeds=(3,),
                 controls=("zero-image", "pool-4x4"), objective="align", steps=7, lr=2.5e-4, batch_size=5,
                 buffer_mib=64, eval_fraction=0.25, eval_split_seed=9, eval_split="lerobot", eval_frames=11,
                 num_denoise_steps=3,
                 lora_rank=2, eval_batch_size=6, recompute="mlp", attention="sdpa", compile=True,
                 device="cuda:1", num_workers=0,
                 cells_per_pass=3,
                 compute_dtype="fp32", results="/r.parquet", out="/o",
                 cache="s3://b/p", progress=False, drop_nonfinite=True, accept_numerics_drift=True, command="x")
EXTRACT = ExtractRequest(dataset="/data", encoder="siglip", grids=("unpooled", "4x4"), cameras=("a", "b"),
                         episodes=(0, 2, 5), weights="/w", random_init=True, seed=4, policy="/p", frame_stride=2,
                         storage_dtype="bf16", compute_dtype="bf16", camera_map="image=a", device="cuda", batch_size=3,
                         num_workers=1, block_frames=16, shard=(1, 4), cache="/c", progress=False,
                         allow_nonfinite=True)


@pytest.mark.parametrize(("command", "request_"), [("fit", FIT), ("extract", EXTRACT)])
def test_a_written_command_line_parses_back_to_the_same_request(command: str, request_: Checked) -> None:
    """Every field with a flag, none at its default, written by sweep.command_line and read by the CLI."""
    flagged = {f.name: getattr(request_, f.name) for f in fields(request_) if declared(type(request_))[f.name].flag}
    assert all(value != declared(type(request_))[name].default for name, value in flagged.items())
    line = command_line(command, type(request_), **flagged)
    args = build_parser().parse_args(shlex.split(line)[1:])
    assert request_from(type(request_), args, **{k: getattr(request_, k) for k in ("command", "extra_manifest")
                                                 if hasattr(request_, k)}) == request_
    assert "--seed 3" in line if command == "fit" else "--shard 1/4" in line  # never `--seeds 3`, a count of 3


def test_one_declaration_is_a_flag_a_recipe_key_and_a_check() -> None:
    """What requests.py's docstring promises for a new field: declared once, refused everywhere."""

    @dataclass(frozen=True)
    class Request(Checked):
        eval_batch_size: int | None = setting(None, rule=POSITIVE, help="frames scored at once")
        mode: str = setting("auto", choices=("auto", "on", "off"))
        grid_only: str = setting("x", recipe=False)

    parser = argparse.ArgumentParser(prog="p", exit_on_error=False)
    add_flags(parser, Request)
    assert request_from(Request, parser.parse_args(["--eval-batch-size", "4", "--mode", "on"])) == \
        Request(eval_batch_size=4, mode="on")
    with pytest.raises(argparse.ArgumentError, match="argument --eval-batch-size: 0 must be > 0"):
        parser.parse_args(["--eval-batch-size", "0"])
    with pytest.raises(argparse.ArgumentError, match="invalid choice: 'maybe'"):
        parser.parse_args(["--mode", "maybe"])
    with pytest.raises(GraftcacheError, match="^eval_batch_size = 0 must be > 0$"):
        Request(eval_batch_size=0)
    with pytest.raises(GraftcacheError, match="^mode = 'maybe' is not one of auto, on, off$"):
        Request.check({"mode": "maybe"})  # a recipe section's overrides
    assert recipe_keys(Request) == ("eval_batch_size", "mode")
    assert "frames scored at once" in parser.format_help()


def test_a_renamed_setting_still_reads_its_former_flag_and_recipe_key_with_a_warning() -> None:
    """`--activation-checkpointing` and the recipe key `activation_checkpointing` (before `recompute`) still set
    the field, each with a FutureWarning naming the new spelling; the written command line uses the new one."""
    parser = build_parser()
    base = ["fit", "--backbone", "smolvla", "--encoder", "e", "--suite", "libero_spatial"]
    with pytest.warns(FutureWarning, match="^--activation-checkpointing is now --recompute; the old flag is deprec"):
        old = parser.parse_args([*base, "--activation-checkpointing", "on"])
    assert old.recompute == "on" and parser.parse_args(base).recompute == "auto"
    with pytest.raises(SystemExit):
        parser.parse_args([*base, "--activation-checkpointing", "sometimes"])  # the same choices
    with pytest.warns(FutureWarning, match=r"^r\.toml \[fit\]: activation_checkpointing is now called recompute"):
        assert renamed(FitRequest, {"activation_checkpointing": "off", "steps": 3}, "r.toml [fit]") == \
            {"recompute": "off", "steps": 3}
    assert "--recompute on" in command_line("fit", FitRequest, recompute="on")


def test_the_console_script_says_a_former_flag_in_one_line() -> None:
    """The console script prints a former flag's Deprecation as one line naming the new spelling, not as a warning
    located in argparse.py (whose line number told the user nothing)."""
    import os
    import subprocess
    import sys

    done = subprocess.run([sys.executable, "-m", "graftcache", "fit", "--activation-checkpointing", "on", "--help"],
                          capture_output=True, text=True, env={**os.environ, "HF_HUB_OFFLINE": "1"}, timeout=120)
    assert done.returncode == 0 and done.stderr.splitlines() == [
        "graftcache: warning: --activation-checkpointing is now --recompute; the old flag is deprecated"]


def test_recipe_tables_take_every_field_but_those_the_product_sets() -> None:
    assert "seeds" not in SECTION_KEYS["fit"] and "steps" in SECTION_KEYS["fit"]
    assert "shard" not in SECTION_KEYS["extract"] and "frame_stride" in SECTION_KEYS["extract"]
    assert SECTION_KEYS["executor"] == tuple(f.name for f in fields(ExecutorSettings))


@pytest.mark.parametrize("command", [["fit", "--backbone", "smolvla", "--encoder", "e", "--suite", "libero_spatial"],
                                     ["extract", "--encoder", "e", "--dataset", "d"]])
def test_no_command_takes_a_bare_dtype(command: list[str], capsys: pytest.CaptureFixture) -> None:
    """One word per dtype: extract stores in --storage-dtype, models compute in --compute-dtype; `--dtype` (fit's
    former refusal, extract's former storage flag) is an unknown argument to both."""
    done = run_cli([*command, "--dtype", "bf16"], capsys)
    assert done.code == 2
    assert done.last == "graftcache: error: unrecognized arguments: --dtype bf16"
    args = build_parser().parse_args(["extract", "--encoder", "e", "--dataset", "d", "--storage-dtype", "bf16"])
    assert args.storage_dtype == "bf16" and not hasattr(args, "dtype")


def test_plain_choices_name_what_the_registries_implement() -> None:
    """The CLI's choices are plain data (building the parser imports no torch); each names a registered entry."""
    from graftcache.fit.controls import CONTROLS as REGISTERED
    from graftcache.fit.data import SPLITS
    from graftcache.fit.objectives import OBJECTIVES as IMPLEMENTED

    assert OBJECTIVES == tuple(IMPLEMENTED)
    assert set(CONTROLS) == set(REGISTERED) - {"none"}
    assert EVAL_SPLITS == tuple(SPLITS)

    from graftcache.backbones.activation_checkpointing import PLANS
    from graftcache.requests import RECOMPUTE_MODES, RECOMPUTE_PLANS

    assert RECOMPUTE_PLANS == tuple(PLANS) and RECOMPUTE_MODES == ("auto", *PLANS)

    from graftcache.analysis.scores import SCORES
    from graftcache.cli.report import SCORE_NAMES

    assert SCORE_NAMES == tuple(SCORES)


def _numeric_fields() -> list[tuple[type, str, type]]:
    from graftcache.analysis.stats import BootSettings
    from graftcache.codecs import without_none
    from graftcache.requests import TinyTrainConfig

    return [(cls, name, without_none(d.hint)) for cls in (ExtractRequest, FitRequest, TinyTrainConfig,
                                                          ExecutorSettings, BootSettings)
            for name, d in declared(cls).items() if without_none(d.hint) in (int, float)]


@pytest.mark.parametrize(("cls", "name", "kind"), _numeric_fields(),
                         ids=lambda x: x if isinstance(x, str) else getattr(x, "__name__", ""))
def test_every_numeric_setting_refuses_what_nothing_downstream_can_take(cls: type, name: str, kind: type) -> None:
    """NaN, infinities, ints past Int64 (the columns and manifests that record them), a float or a bool where an
    int belongs: refused as a request is built, whichever way (Python, a recipe's section, a flag), in one phrase
    naming the field, before any work."""
    from graftcache.cli.common import _parser
    from graftcache.codecs import BadText

    hostile = [float("nan"), float("inf"), float("-inf"), True, *([2**63, -(2**63) - 1, 1.5] if kind is int else [])]
    for value in hostile:
        with pytest.raises(GraftcacheError, match=rf"^{name} = "):
            cls.check({name: value})
    d = declared(cls)[name]
    if d.flag is not None and d.choices is None:
        for text in ("nan", "inf", "-inf", *([str(2**63), "1e3"] if kind is int else ["1e400"])):
            with pytest.raises(BadText):
                _parser(d)(text)
