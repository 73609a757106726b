"""Recipes and counts are checked before any work: `sweep --dry-run` refuses what the real run refuses (and the
real run refuses it before its first step), repeated seeds, suites, encoders and backbones are errors, and
counts that cannot fit memory or disk are refused in one line with the estimate, in-process and cheaply.

Every refusal is checked for: exit code 2, one stderr line naming the place, no traceback, and no work started
(no cache root, no results file)."""

from __future__ import annotations

import re
import resource
import textwrap
from pathlib import Path

import pytest
from helpers.backbones import tiny
from helpers.datasets import Written

from graftcache import budget
from graftcache.checks import MAX_SEED
from graftcache.cli import main

RECIPE = """
    name = "t"
    dataset = "{dataset}"
    results = "{base}/out/results.parquet"
    cache = "{base}/cache"
    suites = {suites}
    seeds = {seeds}
    controls = {controls}
    objective = "{objective}"
    {top}
    [[backbones]]
    name = "smolvla"
    {backbones}
    [[encoders]]
    name = "timm:vit_tiny_patch16_224"
    random_init = true
    {encoders}
    {tables}
"""
DEFAULTS = {"top": "", "suites": '["libero_spatial"]', "seeds": "[0, 1]", "controls": '["native"]', "objective": "flow",
            "backbones": "", "encoders": "", "tables": ""}
#: (recipe changes, what the one stderr line must contain). The v2_pi fixture holds two libero_spatial episodes
#: (0 and 2, one task) and one libero_object episode (1).
BAD = {
    "negative_seed": ({"seeds": "[0, -1]"},
                      "seeds = (0, -1) has seed -1: each must be an integer in 0..9223372036854775807"),
    "repeated_seed": ({"seeds": "[0, 1, 1]"}, "seeds = (0, 1, 1) repeats seed 1: each must be listed once"),
    "path_suite": ({"suites": '["../../x"]'}, "suites: suite = '../../x' is not a suite; choose one of libero_spatial"),
    "repeated_suite": ({"suites": '["libero_spatial", "libero_spatial"]'}, "suites lists 'libero_spatial' twice"),
    "repeated_encoder": ({"encoders": '[[encoders]]\nname = "timm:vit_tiny_patch16_224"\nrandom_init = true\n'},
                         "#1 and #2 of [[encoders]] are the same; list each once"),
    "repeated_backbone": ({"backbones": '[[backbones]]\nname = "smolvla"\npolicy = "tiny"\n'},
                          "#1 and #2 of [[backbones]] are the same; list each once"),
    "repeated_control": ({"controls": '["native", "native"]'},
                         "controls = ('native', 'native') must name each control once"),
    "backbone_with_two_policies": ({"backbones": '[[backbones]]\nname = "smolvla"\npolicy = "/other/policy"\n'},
                                   "#1 and #2 of [[backbones]] both name 'smolvla' (policies 'tiny' and "
                                   "'/other/policy'); a sweep and its report key backbones by name: list each once"),
    "unknown_backbone": ({"backbones": '[[backbones]]\nname = "octo"\n'},
                         "[[backbones]] #2: unknown backbone 'octo'"),
    "suite_not_in_dataset": ({"suites": '["libero_goal"]'},
                             "has no episode of 'libero_goal' (present: libero_object, libero_spatial)"),
    "nothing_to_hold_out": ({"suites": '["libero_object"]'},
                            "suite 'libero_object' of {root}: no episode can be held out"),
    "unknown_objective": ({"objective": "mse"}, "objective = 'mse' is not one of flow, align"),
    "unknown_encoder": ({"encoders": '[[encoders]]\nname = "no-such-encoder"\n'}, "unknown encoder 'no-such-encoder'"),
    "missing_policy": ({"backbones": '[[backbones]]\nname = "pi05"\npolicy = "/nonexistent/policy"\n'},
                       "policy checkpoint '/nonexistent/policy': no such folder"),
    "unknown_recompute": ({"tables": '[fit]\nrecompute = "sometimes"\n'},
                          "[fit]: recompute = 'sometimes' is not one of auto, off, mlp, on"),
    "both_spellings": ({"tables": '[fit]\nrecompute = "on"\nactivation_checkpointing = "on"\n'},
                       "[fit]: activation_checkpointing and recompute are one setting (recompute); keep recompute "
                       "only"),
    "eval_batch_size_zero": ({"tables": '[fit]\neval_batch_size = 0\n'}, "eval_batch_size = 0 must be"),
    "grid_past_memory": ({"tables": '[extract]\ngrids = ["100000x100000"]\n'},
                         "2 camera(s) of grids 100000x100000 x 192 channels needs about"),
    "no_cells_per_pass": ({"tables": '[fit]\ncells_per_pass = 0\n'}, "cells_per_pass = 0 must be > 0"),
    # values no column, allocation or optimiser can take (graftcache.checks.number_problem and the fields' ranges)
    "infinite_lr": ({"tables": '[fit]\nlr = inf\n'}, "[fit]: lr = inf must be a finite number"),
    "diverging_lr": ({"tables": '[train_tiny]\nlr = 1e30\n'}, "[train_tiny]: lr = 1e+30 must be in (0, 1]"),
    "steps_past_int64": ({"tables": '[fit]\nsteps = 9223372036854775808\n'},
                         "[fit]: steps = 9223372036854775808 must be at most 9223372036854775807 in size"),
    "image_size_past_memory": ({"tables": '[train_tiny]\nimage_size = 100000\n'},
                               "[train_tiny]: image_size = 100000 must be in 1..1024"),
    "workers_by_the_thousand": ({"tables": '[extract]\nnum_workers = 5000\n'},
                                "[extract]: num_workers = 5000 must be in 0..1024"),
}


def _recipe(tmp_path: Path, dataset: Path, **changes: str) -> Path:
    path = tmp_path / "recipe.toml"
    values = {**DEFAULTS, **changes}
    path.write_text(textwrap.dedent(RECIPE).format(dataset=dataset, base=tmp_path, **values))
    return path


def _one_line(argv: list[str], capsys: pytest.CaptureFixture) -> str:
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    return err.strip()


def _unmeasured(line: str) -> str:
    """`line` with the machine's memory reading masked: the run reads available memory again, and it moves
    between two readings (CI: 14.9 then 14.8 GiB)."""
    return re.sub(r"(, but [a-z' ]+ is )[\d.]+ [KMGTP]?i?B;", r"\1<measured>;", line)


def _nothing_made(tmp_path: Path) -> None:
    assert not (tmp_path / "cache").exists() and not (tmp_path / "out").exists()


@pytest.mark.parametrize("case", list(BAD))
def test_dry_run_refuses_what_the_run_refuses_before_any_work(case: str, v2_pi: Written, tmp_path: Path,
                                                             capsys: pytest.CaptureFixture) -> None:
    changes, expected = BAD[case]
    path = _recipe(tmp_path, v2_pi.root, **changes)
    expected = expected.format(root=v2_pi.root)
    dry = _one_line(["sweep", "--dry-run", str(path)], capsys)
    assert dry.startswith(f"graftcache sweep: error: {path}") or case in ("unknown_encoder", "grid_past_memory",
                                                                                 "missing_policy")
    assert expected in dry, dry
    run = _one_line(["sweep", str(path)], capsys)
    assert _unmeasured(run) == _unmeasured(dry)  # the real run: the same line, before its first step
    _nothing_made(tmp_path)


def test_dry_run_of_a_good_recipe_prints_the_product_and_makes_nothing(v2_pi: Written, tmp_path: Path,
                                                                    capsys: pytest.CaptureFixture) -> None:
    path = _recipe(tmp_path, v2_pi.root)
    assert main(["sweep", "--dry-run", str(path)]) == 0
    out = capsys.readouterr().out
    # 1 backbone x 1 encoder x 1 suite x 2 seeds x (plain + native) = 4 cells, 4 rows
    assert f"{path}: 4 cells, 4 distinct rows -> {tmp_path}/out/results.parquet" in out
    assert "contents  3 episodes, 18 frames, cameras image, wrist_image" in out
    assert "suite     libero_spatial: 1 train / 1 held-out episodes" in out
    _nothing_made(tmp_path)


def test_dry_run_reads_a_checkpoint_s_cameras_and_grid(v2_pi: Written, tmp_path: Path,
                                                       capsys: pytest.CaptureFixture) -> None:
    """A checkpoint policy's config is read before any step: its cameras must match the dataset's (or be
    mapped), and explicit [extract] grids must hold its token grid (the tiny smolvla's 4x4), which the run
    would otherwise find only after extracting."""
    policy = tiny("smolvla").save(tmp_path / "policy")  # cameras image, image2: v2_pi's are image, wrist_image
    backbone = f'policy = "{policy}"'
    mapped = 'camera_map = "image=image,image2=wrist_image"'
    path = _recipe(tmp_path, v2_pi.root, backbones=backbone, controls="[]", tables='[extract]\ngrids = ["2x2"]\n')
    assert "camera names differ" in _one_line(["sweep", "--dry-run", str(path)], capsys)
    path = _recipe(tmp_path, v2_pi.root, top=mapped, backbones=backbone, controls="[]",
                   tables='[extract]\ngrids = ["2x2"]\n')
    line = _one_line(["sweep", "--dry-run", str(path)], capsys)
    assert line == (f"graftcache sweep: error: {path} [extract]: grids = ['2x2'] lacks 4x4, which the fits read; "
                    "add them, or 'unpooled' to pool them from the encoder's own grid")
    assert _one_line(["sweep", str(path)], capsys) == line
    _nothing_made(tmp_path)
    path = _recipe(tmp_path, v2_pi.root, top=mapped, backbones=backbone, controls="[]",
                   tables='[extract]\ngrids = ["4x4"]\n')
    assert main(["sweep", "--dry-run", str(path)]) == 0


FIT = ["fit", "--backbone", "smolvla", "--encoder", "e", "--suite", "libero_spatial"]


@pytest.mark.parametrize(("argv", "expected"), [
    ([*FIT, "--seeds", "100000000000"], "argument --seeds: '100000000000': --seeds N counts seeds; at most 1000000"),
    ([*FIT, "--seeds", "0-100000000000"], "'0-100000000000' names 100000000001 seeds; at most 1000000"),
    ([*FIT, "--seed", "99999999999999999999999"], f"99999999999999999999999 is past the largest seed, {MAX_SEED}"),
    ([*FIT, "--seed", f"{MAX_SEED + 1}"], f"is past the largest seed, {MAX_SEED}"),
    (["extract", "--encoder", "e", "--dataset", "d", "--episodes", "0-100000000000"],
     "names 100000000001 episodes; at most 10000000"),
    # single values past their fields' rules (graftcache/requests.py), checked as the flag is parsed
    ([*FIT, "--eval-split-seed", f"{MAX_SEED + 1}"],
     f"argument --eval-split-seed: {MAX_SEED + 1} must be in 0..{MAX_SEED}"),
    (["extract", "--encoder", "e", "--dataset", "d", "--seed", "99999999999999999999999"],
     f"argument --seed: 99999999999999999999999 must be in 0..{MAX_SEED}"),
    ([*FIT, "--suite", "../../x"], "argument --suite: '../../x' is not a suite; choose one of libero_spatial"),
    ([*FIT, "--controls", "native,native"], "argument --controls: ('native', 'native') must name each control once"),
    ([*FIT, "--objective", "mse"],
     "argument --objective: invalid choice: 'mse' (choose from 'flow', 'align', 'align-flow')"),
    (["sweep", "recipe.toml", "--cells-per-pass", "0"], "argument --cells-per-pass: 0 must be > 0"),
    # numbers nothing downstream can take: before, a 6.1 TB allocation, a NaN checkpoint, a row Int64 cannot hold
    (["train-tiny", "--backbone", "pi0_fast", "--image-size", "100000"],
     "argument --image-size: 100000 must be in 1..1024"),
    (["train-tiny", "--backbone", "smolvla", "--lr", "inf"], "argument --lr: inf must be a finite number"),
    (["train-tiny", "--backbone", "smolvla", "--weight-decay", "1e300"], "argument --weight-decay: 1e+300 must be in"),
    ([*FIT, "--steps", str(2**63)], f"argument --steps: {2**63} must be at most {MAX_SEED} in size"),
    ([*FIT, "--lora-rank", "1000000000"], "argument --lora-rank: 1000000000 must be in 1..4096"),
    ([*FIT, "--num-workers", "100000"], "argument --num-workers: 100000 must be in 0..1024"),
])
def test_values_past_their_rules_are_refused_at_parse_time(argv: list[str], expected: str,
                                                           capsys: pytest.CaptureFixture) -> None:
    """Refused by argparse, by the field's own rule or choices, before anything is built: a range is measured,
    never expanded (the process grows by far less than the 800 GB that 10**11 seeds would take)."""
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    with pytest.raises(SystemExit) as e:
        main(argv)
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and expected in err.strip().splitlines()[-1], err
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before < 100_000  # KiB


def test_extract_grid_past_memory_is_refused_with_the_estimate(v2_pi: Written, tmp_path: Path,
                                                               capsys: pytest.CaptureFixture) -> None:
    cache = tmp_path / "cache"
    line = _one_line(["extract", "--encoder", "timm:vit_tiny_patch16_224", "--random-init", "--dataset",
                      str(v2_pi.root), "--grids", "100000x100000", "--num-workers", "0", "--no-progress",
                      "--cache", str(cache)], capsys)
    # one block of all 18 frames (block_frames 256), 2 cameras of 64x64 pixels, fp16 features of width 192:
    # three blocks of stored features and one of pixels, plus a batch of 18 pooled in fp32 (and its copy)
    cells, width = 100000 * 100000, 192
    need = 18 * (3 * 2 * cells * width * 2 + 2 * 64 * 64 * 3) + 2 * 18 * cells * width * 4
    assert f"18 frames a block x 2 camera(s) of grids 100000x100000 x 192 channels needs about {budget.size(need)}, " \
           "but " in line  # available memory, or what a container's cgroup limit leaves
    assert "store coarser --grids" in line
    assert not cache.exists()


def test_extract_refuses_a_cache_past_the_free_disk(v2_pi: Written, tmp_path: Path, capsys: pytest.CaptureFixture,
                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    """18 frames x 2 cameras of the encoder's own 14x14 x 192 grid in fp16: 150528 bytes a frame before
    compression, 2.6 MiB in all; with 1 MiB free nothing is written."""
    monkeypatch.setattr(budget, "free_disk", lambda location: (2**20, 2**40))
    cache = tmp_path / "cache"
    line = _one_line(["extract", "--encoder", "timm:vit_tiny_patch16_224", "--random-init", "--dataset",
                      str(v2_pi.root), "--num-workers", "0", "--no-progress", "--cache", str(cache)], capsys)
    assert ": 18 frames x 150528 bytes a frame needs about 2.6 MiB, but the free space of the file system of" in line
    assert "is 1.0 MiB; free space" in line
    assert not cache.exists() or not any(p.is_dir() for p in cache.iterdir())
