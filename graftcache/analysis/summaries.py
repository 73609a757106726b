"""Per-cell summaries of a results table: seed statistics, ranks, the top tier (near-tie band), gaps."""

from __future__ import annotations

import polars as pl

from graftcache.analysis.stats import BASIS_MISSING, BootSettings, Bootstrap, cells_of, prob_greater
from graftcache.analysis.table import CELL, GROUP, PLAIN, RECIPE_COLUMNS, check, control_rows


def duplicate_rows(results: pl.DataFrame) -> pl.DataFrame:
    """Keys (backbone, suite, encoder, control, seed) held by more than one row, with the recipe columns
    whose values differ among them: such a table mixes recipes and must be filtered before ranking.
    Recipe columns the table lacks (a minimal table) cannot differ and are not compared."""
    check(results)
    keys = [*CELL, "control", "seed"]
    recipe = [c for c in RECIPE_COLUMNS if c in results.columns]
    dup = results.group_by(keys).agg(
        n=pl.len().cast(pl.Int64), **{c: pl.col(c).n_unique().cast(pl.Int64) for c in recipe}
    )
    differing = (
        pl.concat_list([pl.when(pl.col(c) > 1).then(pl.lit(c)) for c in recipe]).list.drop_nulls()
        if recipe
        else pl.lit([], dtype=pl.List(pl.String))
    )
    return dup.filter(pl.col("n") > 1).select(*keys, "n", differing=differing).sort(keys)


def seed_summary(results: pl.DataFrame, control: str = PLAIN) -> pl.DataFrame:
    """Mean, std (ddof=1), n, min, max of eval_mse over seeds per (backbone, suite, encoder).

    The grid is every backbone x every (suite, encoder) seen among the control's rows, so an encoder run on
    one backbone only shows up on the other as `status == "missing"` with n == 0 and null statistics.
    status: "ok" (>= 2 valid seeds), "single seed", "no valid eval_mse" (all null/non-finite), "missing".
    """
    rows = control_rows(results, control)
    valid = pl.col("eval_mse").is_not_null()
    stats = rows.group_by(CELL).agg(
        n=pl.col("eval_mse").count().cast(pl.Int64),
        n_rows=pl.len().cast(pl.Int64),
        mean=pl.col("eval_mse").mean(),
        std=pl.col("eval_mse").std(ddof=1),
        min=pl.col("eval_mse").min(),
        max=pl.col("eval_mse").max(),
        seeds=pl.col("seed").filter(valid).sort(),
    )
    grid = rows.select("backbone").unique().join(rows.select("suite", "encoder").unique(), how="cross")
    out = grid.join(stats, on=CELL, how="left").with_columns(pl.col("n", "n_rows").fill_null(0))
    n, n_rows = pl.col("n"), pl.col("n_rows")
    status = (
        pl.when(n_rows == 0)
        .then(pl.lit("missing"))
        .when(n == 0)
        .then(pl.lit("no valid eval_mse"))
        .when(n == 1)
        .then(pl.lit("single seed"))
        .otherwise(pl.lit("ok"))
    )
    return (
        out.with_columns(n_invalid=n_rows - n, status=status)
        .select(*CELL, "n", "mean", "std", "min", "max", "seeds", "n_rows", "n_invalid", "status")
        .sort(CELL)
    )


def rankings(results: pl.DataFrame) -> pl.DataFrame:
    """seed_summary plus `rank` per (backbone, suite): 1 = lowest mean MSE, equal means share the lowest
    rank ("min" ranking: 1, 1, 3); missing cells get a null rank. `n_ranked` counts ranked encoders."""
    return (
        seed_summary(results)
        .with_columns(
            rank=pl.col("mean").rank("min").over(GROUP).cast(pl.Int64),
            n_ranked=pl.col("mean").count().over(GROUP).cast(pl.Int64),
        )
        .sort([*GROUP, "rank", "encoder"], nulls_last=True)
    )


def near_tie_band(results: pl.DataFrame, *, boot: BootSettings = BootSettings()) -> pl.DataFrame:
    """rankings plus the top tier per (backbone, suite).

    Columns added: `best` (lowest mean; alphabetical first among exact ties), `p_worse` =
    P(mean_enc* > mean_best*) under the bootstrap (null for the best itself and for missing cells),
    `in_band` = p_worse < boot.confidence (null when the cell is missing), `basis` (see the
    graftcache.analysis docstring).
    """
    ranks = rankings(results)
    replicates = Bootstrap(results, PLAIN, boot)
    records = []
    for (backbone, suite), group in ranks.group_by(GROUP, maintain_order=True):
        ranked = group.drop_nulls("mean").sort("mean", "encoder")
        best = ranked["encoder"][0] if len(ranked) else None
        for enc in group["encoder"]:
            rec = {
                "backbone": backbone,
                "suite": suite,
                "encoder": enc,
                "best": best,
                "p_worse": None,
                "in_band": None,
                "basis": BASIS_MISSING,
            }
            key = (backbone, suite, enc)
            if key in replicates.cells and best is not None:
                kb = (backbone, suite, best)
                p, rec["basis"] = prob_greater(replicates, key, replicates, kb)
                rec["p_worse"], rec["in_band"] = (None, True) if enc == best else (p, p < boot.confidence)
            records.append(rec)
    band = pl.DataFrame(
        records,
        schema={
            **dict.fromkeys(CELL, pl.String),
            "best": pl.String,
            "p_worse": pl.Float64,
            "in_band": pl.Boolean,
            "basis": pl.String,
        },
    )
    return ranks.join(band, on=CELL, how="left", maintain_order="left")


def missing_cells(results: pl.DataFrame) -> pl.DataFrame:
    """Every gap in the plain-graft grid, one row per problem: a (backbone, suite, encoder) with no rows,
    rows with null/non-finite eval_mse, and seeds run for other encoders of the same (backbone, suite) but
    not for this one."""
    summary = seed_summary(results)
    seeds = summary.group_by(GROUP).agg(
        all_seeds=pl.col("seeds").list.explode(keep_nulls=False, empty_as_null=False).unique().sort()
    )
    records = []
    for row in summary.join(seeds, on=GROUP, how="left").iter_rows(named=True):
        where = {k: row[k] for k in CELL}
        if row["status"] == "missing":
            records.append({**where, "problem": "no plain-graft rows"})
            continue
        if row["n_invalid"]:
            records.append(
                {**where, "problem": f"{row['n_invalid']} row(s) with null or non-finite eval_mse"}
            )
        lacking = sorted(set(row["all_seeds"]) - set(row["seeds"] or []))
        if lacking and row["n"]:
            records.append({**where, "problem": "missing seed(s) " + ", ".join(map(str, lacking))})
    return pl.DataFrame(records, schema={**dict.fromkeys(CELL, pl.String), "problem": pl.String})


def episode_coverage(results: pl.DataFrame) -> tuple[int, int]:
    """(plain-graft cells whose every valid row carries per-episode MSEs, plain-graft cells with valid rows).

    Only the first kind gets the two-level bootstrap; the report states which bootstrap its tiers rest on,
    since a table without EPISODE_COLUMN (older versions, other tools, a paper) falls back to seeds only.
    """
    cells = cells_of(control_rows(results, PLAIN))
    return sum(c.episodes is not None for c in cells.values()), len(cells)
