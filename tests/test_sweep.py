"""Sweep recipes: parsing and its errors, and a whole small sweep (train-tiny -> extract -> fit -> rows)
that a rerun skips entirely."""

from __future__ import annotations

import shlex
import textwrap
from pathlib import Path

import polars as pl
import pytest
from helpers.datasets import Written

from graftcache import results
from graftcache.cli import main
from graftcache.errors import GraftcacheError
from graftcache.export.bundle import cell_of, run_folder
from graftcache.fit.controls import get_control
from graftcache.fit.run import saved_cell
from graftcache.recipe import SECTION_KEYS, RecipeError, load_recipe
from graftcache.store import FeatureCache, list_caches
from graftcache.sweep import SweepState, encoder_grids, run_sweep

ROOT = Path(__file__).resolve().parents[1]


def _write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "recipe.toml"
    path.write_text(textwrap.dedent(text))
    return path


BASE = """
    name = "t"
    dataset = "{dataset}"
    results = "{results}"
    suites = ["libero_spatial"]
    seeds = [0]
    controls = {controls}
    [[backbones]]
    name = "smolvla"
    [[encoders]]
    name = "timm:vit_tiny_patch16_224"
    random_init = true
    seed = 3
"""


# Counted by hand from the recipe files (2 backbones and 2 suites in both):
# demo.toml: 3 encoders, seeds [0, 1], 4 controls (native, native-graft, zero-image, shuffled-image).
#   cells visited: 2 backbones x 3 encoders x 2 suites x 2 seeds x (plain + 4 controls) = 120;
#   rows: per (backbone, suite, seed) 3 encoders x (plain, zero-image, shuffled-image) + 1 native
#   + 1 native-graft (the native tower's rows do not depend on the encoder) = 11, x 2 x 2 x 2 = 88.
# paper.toml: 4 encoders, seeds [0, 1, 2], 7 controls (the demo's 4 + pool-4x4, pool-16x16, lora).
#   cells: 2 x 4 x 2 x 3 x (1 + 7) = 384; rows: 4 x (plain + 5 encoder controls) + 2 native = 26,
#   x 2 backbones x 2 suites x 3 seeds = 312.
@pytest.mark.parametrize(("name", "cells", "rows"), [("demo.toml", 120, 88), ("paper.toml", 384, 312)])
def test_shipped_recipes_parse(name: str, cells: int, rows: int) -> None:
    recipe = load_recipe(ROOT / "cli" / name)
    assert {b.name for b in recipe.backbones} == {"smolvla", "pi05"}
    assert set(recipe.suites) == {"libero_spatial", "libero_object"}
    assert {"native", "native-graft", "zero-image", "shuffled-image"} <= set(recipe.controls)
    assert (recipe.n_fits, recipe.n_rows) == (cells, rows)
    if name == "demo.toml":  # the bundled sample, found relative to the recipe's folder
        assert recipe.dataset == str((ROOT / "data" / "libero_sample").resolve())
        assert {"mobilenetv2", "efficientnet-lite0"} <= {e.name for e in recipe.encoders}
        assert any(e.random_init for e in recipe.encoders)
    else:
        assert recipe.dataset == "lerobot/libero" and len(recipe.seeds) == 3 and len(recipe.encoders) >= 4


def test_zoo_recipe_names_every_backbone_by_a_hub_id() -> None:
    """cli/zoo.toml (never run here: released policies only) lists every registered backbone that has a checkpoint
    to load, and says why of each it leaves out (Wall-X: no lerobot-format checkpoint exists). Counted by hand:
    9 backbones x 4 encoders x 2 suites x 3 seeds x (plain + 6 controls) = 1512 cells; rows per (backbone, suite,
    seed): 4 encoders x (plain, zero-image, shuffled-image, pool-4x4, lora) + native + native-graft = 22, x 9 x 2 x
    3 = 1188."""
    from graftcache.backbone_registry import BACKBONES

    text = (ROOT / "cli" / "zoo.toml").read_text()
    recipe = load_recipe(ROOT / "cli" / "zoo.toml")
    listed = [b.name for b in recipe.backbones]
    assert sorted(set(BACKBONES) - set(listed)) == ["wall_x"] and "# Not here: wall_x" in text
    assert all(b.policy != "tiny" and b.policy.count("/") == 1 for b in recipe.backbones)
    assert {b.name: b.policy for b in recipe.backbones}["pi0_fast"] == "lerobot/pi0fast_base"
    assert listed[0] == "smolvla" and listed[-1] == "pi05"  # smallest to largest, as its comment lists them
    assert (recipe.n_fits, recipe.n_rows) == (1512, 1188) and recipe.dataset == "lerobot/libero"


def test_section_keys_are_fields_of_the_requests_they_override() -> None:
    from dataclasses import fields

    from graftcache.extract import ExtractRequest
    from graftcache.fit.run import FitRequest
    from graftcache.pretrain import TinyTrainConfig

    for section, cls in (("extract", ExtractRequest), ("fit", FitRequest), ("train_tiny", TinyTrainConfig)):
        assert set(SECTION_KEYS[section]) <= {f.name for f in fields(cls)}, section


def test_unknown_missing_and_invalid_keys_name_file_and_key(tmp_path: Path) -> None:
    base = BASE.format(dataset="x", results="r.parquet", controls='["native"]')
    with pytest.raises(RecipeError, match=r"recipe.toml \[fit\]: unknown key\(s\) stepz"):
        load_recipe(_write(tmp_path, base + "[fit]\nstepz = 3\n"))
    with pytest.raises(RecipeError, match=r"\[\[encoders\]\] #2: unknown key\(s\) nmae"):
        load_recipe(_write(tmp_path, base + '[[encoders]]\nnmae = "siglip"\n'))
    with pytest.raises(RecipeError, match="missing key.*seeds"):
        load_recipe(_write(tmp_path, base.replace("seeds = [0]", "")))
    with pytest.raises(RecipeError, match="controls: unknown control 'blur'"):
        load_recipe(_write(tmp_path, BASE.format(dataset="x", results="r", controls='["blur"]')))
    with pytest.raises(RecipeError, match="not valid TOML"):
        load_recipe(_write(tmp_path, "name = \n"))
    with pytest.raises(RecipeError, match="no such recipe file"):
        load_recipe(tmp_path / "absent.toml")
    assert main(["sweep", str(tmp_path / "absent.toml")]) == 2


def test_extract_grids_default_to_unpooled_and_explicit_ones_must_cover_the_fits(tmp_path: Path) -> None:
    base = BASE.format(dataset="x", results="r", controls='["pool-2x2"]')
    state = SweepState(token_grids={"smolvla": (4, 4)})
    assert encoder_grids(load_recipe(_write(tmp_path, base)), state) == ("unpooled",)
    explicit = load_recipe(_write(tmp_path, base + '[extract]\ngrids = ["unpooled", " 3x3"]\n'))
    assert explicit.extract["grids"] == ("unpooled", " 3x3") and encoder_grids(explicit, state) == ("unpooled", "3x3")
    covered = load_recipe(_write(tmp_path, base + '[extract]\ngrids = ["4x4", "2x2"]\n'))
    assert encoder_grids(covered, state) == ("4x4", "2x2")
    short = load_recipe(_write(tmp_path, base + '[extract]\ngrids = ["2x2"]\n'))
    with pytest.raises(GraftcacheError, match=r"recipe.toml \[extract\]: grids = \['2x2'\] lacks 4x4, which the fits"):
        encoder_grids(short, state)
    with pytest.raises(RecipeError,
                       match=r"recipe.toml \[extract\]: grids = \('4y4',\) must name grids: unpooled or HxW"):
        load_recipe(_write(tmp_path, base + '[extract]\ngrids = ["4y4"]\n'))
    with pytest.raises(RecipeError, match=r"\[extract\]: grids = \(\(4, 4\),\) is not a tuple"):
        load_recipe(_write(tmp_path, base + '[extract]\ngrids = [[4, 4]]\n'))


def test_hub_ids_pass_through_and_local_folders_resolve(tmp_path: Path) -> None:
    (tmp_path / "ds").mkdir()
    local = load_recipe(_write(tmp_path, BASE.format(dataset="ds", results="r", controls="[]")))
    assert local.dataset == str((tmp_path / "ds").resolve())
    hub = load_recipe(_write(tmp_path, BASE.format(dataset="lerobot/libero", results="r", controls="[]")))
    assert hub.dataset == "lerobot/libero"


def test_small_sweep_end_to_end_then_rerun_skips(tmp_path: Path, v3_video: Written,
                                                 capsys: pytest.CaptureFixture) -> None:
    out = tmp_path / "results.parquet"
    top = f'cache = "{tmp_path / "cache"}"\n'  # top-level keys go before the first table
    base = BASE.format(dataset=v3_video.root, results=out, controls='["native", "pool-2x2"]')
    text = top + base + textwrap.dedent("""
        [extract]
        batch_size = 8
        num_workers = 0
        [fit]
        steps = 2
        batch_size = 4
        eval_frames = 4
        num_denoise_steps = 2
        [train_tiny]
        steps = 2
        batch_size = 4
    """)
    recipe = load_recipe(_write(tmp_path, text))
    lines: list[str] = []
    state = run_sweep(recipe, log=lines.append)
    rows = results.read(out)
    # 1 backbone x 1 encoder x 1 suite x 1 seed x (plain, native, pool-2x2): 3 cells, 3 rows written
    assert rows.height == recipe.n_rows == recipe.n_fits == 3
    assert sorted(rows["control"].to_list()) == ["native", "none", "pool-2x2"]
    assert rows.filter(pl.col("control") == "native")["encoder"].to_list() == ["smolvla-native"]
    assert rows["random_init"].all() and (rows["suite"] == "libero_spatial").all()
    assert set(state.commands) >= {"policy smolvla", *state.encoder_caches.values(), *state.native_caches.values()}
    # one cache for the encoder, its own 14x14 grid alone, read at the backbone's 4x4 and the control's 2x2
    key = state.encoder_caches[recipe.encoders[0]]
    (cache,) = [c for c in list_caches(tmp_path / "cache") if c.manifest.encoder_name == recipe.encoders[0].name]
    assert cache.key == key and cache.manifest.grids == ["14x14"] and cache.manifest.unpooled_grid == "14x14"
    grafts = rows.filter(pl.col("encoder") == recipe.encoders[0].name).sort("control")
    assert grafts["cache_key"].to_list() == [key, key] and grafts["pool_grid"].to_list() == ["4x4", "2x2"]
    native = FeatureCache(tmp_path / "cache" / state.native_caches["smolvla"])
    assert native.manifest.grids == ["4x4"] and "connector" in native.manifest.extras  # its backbone's grid
    # the recorded commands rebuild the very caches the sweep made
    for made in (key, native.key):
        assert "--grids" in state.commands[made] and "--batch-size 8 --num-workers 0" in state.commands[made]
        assert main([*shlex.split(state.commands[made])[1:], "--cache", str(tmp_path / "cache"), "--no-progress"]) == 0
        assert capsys.readouterr().out.strip().splitlines()[-1] == made
    # a sweep's rows give back their cells for `graftcache export` from the row alone (no command line parsed back,
    # no run folder read: the native one has none), each the cell its run folder recorded where it trained one
    for row in rows.iter_rows(named=True):
        assert cell_of(row, None).run_id == row["run_id"]
        if get_control(row["control"]).train:
            assert saved_cell(run_folder(row, out, str(tmp_path / "cache"), None)) == cell_of(row, None)

    again: list[str] = []
    run_sweep(recipe, log=again.append)
    assert results.read(out).height == 3
    (skip,) = [line for line in again if "skip" in line]  # the request's 3 finished cells, in one line
    assert skip.startswith(f"skip smolvla/{recipe.encoders[0].name}/libero_spatial: 3 cells already in ")
    assert any("reusing complete cache" in line for line in again)
    assert any("reusing tiny smolvla trained by train-tiny" in line for line in again)
