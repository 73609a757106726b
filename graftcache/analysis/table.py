"""What every question reads from a results table: control names, grouping keys, backbone labels, and the
rows of one control with diverged fits marked invalid."""

from __future__ import annotations

import functools

import polars as pl

from graftcache.errors import GraftcacheError
from graftcache.requests import NATIVE_CONTROL, NATIVE_GRAFT_CONTROL
from graftcache.results import REPORT_COLUMNS

PLAIN = "none"
ZERO_IMAGE = "zero-image"
SHUFFLED_IMAGE = "shuffled-image"
NOT_ENCODER_CONTROLS = (PLAIN, NATIVE_CONTROL, NATIVE_GRAFT_CONTROL)

EPISODE_COLUMN = "eval_mse_episodes"

CELL = ["backbone", "suite", "encoder"]
GROUP = ["backbone", "suite"]
RECIPE_COLUMNS = ("policy", "objective", "pool_grid", "steps", "lr", "batch_size", "eval_split_seed", "eval_split")


@functools.cache
def backbone_label(name: str) -> str:
    """How the paper writes a backbone name, its spec's `label` ("pi05" -> "pi0.5"); unknown names pass through."""
    from graftcache.backbones import registered_spec  # imports the backbone's adapter (torch) on first use

    spec = registered_spec(name)
    return name if spec is None else spec.label


def check(results: pl.DataFrame) -> None:
    """The columns every question needs (results.REPORT_COLUMNS); all others are optional here."""
    missing = [c for c in REPORT_COLUMNS if c not in results.columns]
    if missing:
        raise GraftcacheError(f"results table lacks column(s) {missing}")


def control_rows(results: pl.DataFrame, control: str) -> pl.DataFrame:
    """Rows of one control with non-finite eval_mse turned into null (counted as invalid, never averaged)."""
    check(results)
    mse = pl.col("eval_mse")
    return results.filter(pl.col("control") == control).with_columns(
        eval_mse=pl.when(mse.is_finite()).then(mse).otherwise(None)
    )


def plain_suites(results: pl.DataFrame) -> list[str]:
    """Suites with plain-graft rows, sorted."""
    return sorted(control_rows(results, PLAIN)["suite"].unique().to_list())


def plain_backbones(results: pl.DataFrame) -> set[str]:
    """Backbones with at least one valid plain-graft MSE."""
    return set(control_rows(results, PLAIN).drop_nulls("eval_mse")["backbone"].unique().to_list())
