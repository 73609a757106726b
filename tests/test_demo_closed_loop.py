"""`graftcache demo --closed-loop`'s choice of cells (graftcache/demo_closed_loop.py), on tests/helpers/tables.py's
hand-built results with native repeats and pi05 zero-image rows added. The command itself (fits, then 30 minutes
in the simulator) is measured by hand and quoted in the README, not run in CI; its pieces (rollout, graded progress,
workers, report) are tested in tests/rollout and tests/report."""

from __future__ import annotations

import hashlib

import polars as pl
import pytest
from helpers.tables import control_rows, plain_rows, row, table

from graftcache.demo_closed_loop import ClosedLoopPlan, closed_loop_run_ids
from graftcache.errors import GraftcacheError

PLAN = ClosedLoopPlan(figure=("smolvla", "libero_spatial"), paired_seeds=(0, 1))


def _one_policy_per_seed(r: dict) -> dict:
    """A zero-image row as format 6 writes it: one policy per (backbone, suite, seed) whatever the encoder (its
    features zeroed, its cache's frames those of every encoder's cache)."""
    if r["control"] == "zero-image":
        r["policy_id"] = hashlib.sha256(f"{r['backbone']} {r['suite']} {r['seed']}".encode()).hexdigest()[:16]
    return r


def _results() -> pl.DataFrame:
    native_repeats = [row("smolvla", "libero_spatial", "smolvla-native", s, 1.0, control="native") for s in (1, 2)]
    pi05_zero = [row("pi05", "libero_spatial", "dinov2-s", s, 4.0, control="zero-image") for s in (0, 1, 2)]
    return table([_one_policy_per_seed(r) for r in plain_rows() + control_rows() + native_repeats + pi05_zero])


def test_every_live_cell_of_the_figure_and_native_against_zero_image_elsewhere() -> None:
    """Each policy once: native of seed 0 alone (its rows of every seed are one policy: the upgrade's policy_id of a
    cell that trains nothing), and of the zero-image rows of siglip and resnet18 (one policy per seed) resnet18's,
    the first encoder by name; each choice said in one line."""
    results = _results()
    lines: list[str] = []
    cells = closed_loop_run_ids(results, PLAN, lines.append)
    chosen = results.filter(pl.col("run_id").is_in([*cells.figure, *cells.paired]))
    keys = set(chosen.select("backbone", "suite", "encoder", "control", "seed").rows())
    paired = results.filter(pl.col("run_id").is_in(cells.paired))
    figure = results.filter((pl.col("backbone") == "smolvla") & (pl.col("suite") == "libero_spatial"))
    expected_figure = {k for k in figure.select("backbone", "suite", "encoder", "control", "seed").rows()
                       if k[3] != "shuffled-image" and not (k[3] == "native" and k[4] > 0)
                       and not (k[3] == "zero-image" and k[2] == "siglip")}
    # pi05/libero_spatial: its best encoder is dinov2-s (1.4 < siglip 1.5): its zero-image rows of seeds 0 and 1
    expected_others = {("pi05", "libero_spatial", "pi05-native", "native", 0),
                       ("pi05", "libero_spatial", "dinov2-s", "zero-image", 0),
                       ("pi05", "libero_spatial", "dinov2-s", "zero-image", 1)}
    assert keys == expected_figure | expected_others
    assert set(paired.select("backbone", "suite", "encoder", "control", "seed").rows()) == expected_others
    assert not set(cells.figure) & set(cells.paired)
    assert len(expected_figure) == 3 * 3 + 3 + 3 + 1  # 3 encoders, zero-image, native-graft x 3 seeds; native
    assert chosen.height == len(keys)  # each once
    zero = results.filter((pl.col("control") == "zero-image") & (pl.col("suite") == "libero_spatial")
                          & (pl.col("backbone") == "smolvla")).sort("seed", "encoder")
    for seed in range(3):
        first, other = zero.filter(pl.col("seed") == seed)["run_id"].to_list()  # resnet18's, siglip's
        assert sum(line.startswith(f"runs {other} are the policy of run {first} (smolvla/resnet18/libero_spatial "
                                   f"control zero-image seed {seed}, ") for line in lines) == 1
    native = results.filter((pl.col("control") == "native") & (pl.col("backbone") == "smolvla")).sort("seed")
    assert any(line.startswith(f"runs {', '.join(native['run_id'][1:])} are the policy of run {native['run_id'][0]} ")
               for line in lines)


def test_a_figure_without_rows_is_refused() -> None:
    with pytest.raises(GraftcacheError, match="no row of smolvla on libero_90"):
        closed_loop_run_ids(_results(), ClosedLoopPlan(figure=("smolvla", "libero_90")))


def test_the_dose_recipe_is_the_figure_s_backbone_suite_and_dose_encoder() -> None:
    from graftcache.demo import DEFAULT_RECIPE
    from graftcache.demo_closed_loop import CLOSED_LOOP, _dose_recipe
    from graftcache.recipe import load_recipe

    recipe = load_recipe(DEFAULT_RECIPE)
    dose = _dose_recipe(recipe, CLOSED_LOOP)
    assert ([b.name for b in dose.backbones], [e.name for e in dose.encoders], dose.suites) == (
        ["smolvla"], ["efficientnet-lite0"], ("libero_object",))
    assert dose.controls == ("noise-0.25", "noise-0.5", "noise-0.75", "noise-0.9") and dose.seeds == recipe.seeds
    with pytest.raises(GraftcacheError, match="no backbone smolvla or no encoder dinov2-s: the dose family"):
        _dose_recipe(recipe, ClosedLoopPlan(dose_encoder="dinov2-s"))
