"""The zoo backbones end to end on the bundled LIBERO sample, in this process: `train-tiny`, `extract --encoder
<name>-native` (and a candidate encoder), then `fit` with every control. Few steps and a strided subset of
four episodes keep it cheap; what is checked is that each command runs the backbone's real code paths and
writes what the next one reads."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
from helpers.probes import run_cli

from graftcache import results
from graftcache.backbones import get_backbone
from graftcache.store import FeatureCache

SAMPLE = Path(__file__).resolve().parents[1] / "data" / "libero_sample"
ENCODER = "timm:vit_tiny_patch16_224"
CONTROLS = ("native", "native-graft", "zero-image", "shuffled-image", "pool-2x2", "lora")
SUBSET = ["--dataset", str(SAMPLE), "--episodes", "0-3", "--frame-stride", "8", "--num-workers", "0",
          "--batch-size", "16", "--no-progress"]
#: backbone -> (native token grid, the tower's own grid before its connector, post-connector tokens per camera, LM
#: width) of its tiny configuration (the Qwen ViTs of EO-1, GR00T, Wall-X and VLA-JEPA, and EVO1's InternViT: 8x8
#: patches, merged 2x2 by their connectors)
TINY = {"xvla": ((4, 4), (4, 4), 17, 64), "pi0": ((4, 4), (4, 4), 16, 128), "pi0_fast": ((4, 4), (4, 4), 16, 128),
        "eo1": ((4, 4), (8, 8), 16, 64), "evo1": ((4, 4), (8, 8), 16, 64), "groot": ((4, 4), (8, 8), 16, 64),
        "wall_x": ((4, 4), (8, 8), 16, 64), "vla_jepa": ((4, 4), (8, 8), 16, 64)}


@pytest.mark.slow  # ~1-2 min per backbone on 2 cores: 1 native step, two small extractions, 7 tiny fits
@pytest.mark.parametrize("name", sorted(TINY))
def test_train_tiny_extract_native_and_fit_every_control(name: str, tmp_path: Path, capsys) -> None:
    grid, tower_grid, tokens, width = TINY[name]
    policy, cache, table = tmp_path / "policy", tmp_path / "cache", tmp_path / "results.parquet"
    done = run_cli(["train-tiny", "--backbone", name, "--dataset", str(SAMPLE), "--steps", "1", "--out", str(policy),
                    "--cache", str(cache)], capsys)
    assert done.code == 0, done.err[-2000:]
    record = json.loads((policy / "graftcache_pretrain.json").read_text())
    assert record["backbone"] == name and record["cameras"] == ["image", "image2"]
    assert get_backbone(name).read_token_grid(policy) == grid

    native = run_cli(["extract", "--encoder", f"{name}-native", "--policy", str(policy), *SUBSET,
                      "--cache", str(cache)], capsys)
    assert native.code == 0, native.err[-2000:]
    manifest = FeatureCache(cache / native.out.split()[-1]).manifest
    assert tuple(manifest.encoder["grid"]) == tower_grid and manifest.extras["connector"] == [tokens, width]
    candidate = run_cli(["extract", "--encoder", ENCODER, "--random-init", *SUBSET, "--cache", str(cache)], capsys)
    assert candidate.code == 0, candidate.err[-2000:]

    fit = run_cli(["fit", "--backbone", name, "--policy", str(policy), "--encoder", ENCODER, "--dataset",
                   str(SAMPLE), "--suite", "libero_spatial", "--seeds", "1", "--controls", ",".join(CONTROLS),
                   "--steps", "2", "--batch-size", "4", "--eval-fraction", "0.5", "--eval-frames", "4",
                   "--num-denoise-steps", "2", "--cache", str(cache), "--results", str(table), "--no-progress"],
                  capsys)
    assert fit.code == 0, fit.err[-2000:]
    rows = results.read(table)
    assert sorted(rows["control"]) == sorted(("none", *CONTROLS)) and set(rows["backbone"]) == {name}
    assert all(math.isfinite(v) and v > 0 for v in rows["eval_mse"])
    by_control = {r["control"]: r for r in rows.iter_rows(named=True)}
    assert by_control["native"]["encoder"] == f"{name}-native" and by_control["native"]["objective"] == "eval"
    assert by_control["pool-2x2"]["pool_grid"] == "2x2" and by_control["none"]["pool_grid"] == f"{grid[0]}x{grid[1]}"
    assert by_control["lora"]["eval_mse"] != by_control["none"]["eval_mse"]  # the adapters trained too
