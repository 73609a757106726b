"""The one upgrade path for results files: rows of an older format read as rows of this one, or refused in one line
saying why and how to rebuild them."""

from __future__ import annotations

from pathlib import Path

import polars as pl

import graftcache
from graftcache.cameras import parse_camera_map, renames
from graftcache.errors import ResultsError
from graftcache.results.schema import (
    ADDED_TO_CELLS,
    CELL_COLUMNS,
    FORMAT_VERSION,
    IDENTITY_VERSION,
    REPORT_COLUMNS,
    SCHEMA,
    make_policy_id,
)

#: The oldest results format read: rows of earlier ones hash cells of another shape into their run_ids.
OLDEST = IDENTITY_VERSION

#: What a row without a column of a later format (of format 3, of format 4 written before random_init was split,
#: of format 4 before format 5 recorded every cell field) held in it, where its other columns say so: random_init is
#: the union of the encoder's and the backbone's, so a row whose random_init is false had neither, and a true one
#: leaves both unknown (null); a cell holds lora_rank 0 but for the lora control (whose rank only its run folder's
#: cell records). The other cell fields format 5 added (eval_fraction, eval_frames, num_denoise_steps) stay null:
#: such a row's cell is read from its run folder (graftcache.export.bundle.cell_of).
DERIVED: dict[str, pl.Expr] = {
    "encoder_random_init": pl.when(~pl.col("random_init")).then(False),
    "backbone_random_init": pl.when(~pl.col("random_init")).then(False),
    "lora_rank": pl.when(pl.col("control") != "lora").then(0),
}

#: The cell fields the policy_id of a row written without one leaves out, where the row's other columns say its policy
#: ignored them: a cell evaluated as loaded (objective "eval": the native control) draws nothing from its seed, as
#: graftcache.fit.controls.Control.ignores declares for the cells written now. A zero-image row of such a format keeps
#: its cache_key: its projector then started from a random init drawn at the encoder's width.
IGNORED_BEFORE: dict[str, pl.Expr] = {"seed": pl.col("objective") == "eval"}


def upgrade(rows: pl.DataFrame, path: Path) -> pl.DataFrame:
    """The one upgrade path for results files: rows of this format as they are; rows of formats 3 and 4 (their
    run_ids hash cells as this format's do: IDENTITY_VERSION), and rows of a format written before it gained a
    column, with the columns they lack, each holding ADDED_TO_CELLS' value, what DERIVED derives from the row, or
    null; rows of an older format (format 1 had no format_version column; format 2 hashed `pool_grid="native"` and
    the format version 2 into its run_ids) are refused in one line with the commands that rebuild them, since their
    run_ids hash cells of another shape: a rerun could not skip their cells and would write each twice. Rows of a
    newer format (a later graftcache wrote them) and tables that are no graftcache results at all (no run_id or
    report column) are refused as such."""
    current = "format_version" in rows.columns and rows["format_version"].eq(FORMAT_VERSION).all()
    if current and set(SCHEMA) <= set(rows.columns):
        return rows
    if "format_version" in rows.columns and rows["format_version"].is_in(range(OLDEST, FORMAT_VERSION + 1)).all():
        return _from_older(rows)
    lacking = [c for c in ("run_id", *REPORT_COLUMNS) if c not in rows.columns]
    if lacking:
        raise ResultsError(f"{path}: not a graftcache results table (no column {', '.join(lacking)}); pass another "
                           "--results")
    if "format_version" in rows.columns:
        newer = rows.filter(pl.col("format_version") > FORMAT_VERSION)
        if newer.height:
            raise ResultsError(f"{path}: {newer.height} row(s) of results format {newer['format_version'].max()}, "
                               f"newer than this graftcache's ({FORMAT_VERSION}, graftcache {graftcache.__version__}): "
                               "read it with the graftcache that wrote it, or pass another --results")
    old = rows if "format_version" not in rows.columns else rows.filter(pl.col("format_version") < OLDEST)
    recorded = old["command"].drop_nulls().unique(maintain_order=True).to_list() if "command" in old.columns else []
    commands = [c for c in recorded if c.startswith("graftcache ")]  # older graftcache recorded `fit` alone
    rebuild = f"`{commands[0]}`" if commands else "the fits or sweeps that wrote them (its rows record no command line)"
    more = f" (and {len(commands) - 1} other command(s) its rows record)" if len(commands) > 1 else ""
    raise ResultsError(f"{path}: {old.height} row(s) of an older results format than {OLDEST} (run_ids "
                       f"of cells of another shape); move the file aside and rebuild it: {rebuild}{more}")


def _from_older(rows: pl.DataFrame) -> pl.DataFrame:
    """Rows of formats OLDEST..FORMAT_VERSION as this format: the columns they lack added, null but where
    ADDED_TO_CELLS knows what rows of a format before a cell field's held (also filled on such rows of a table that
    has the column) or DERIVED derives it."""
    lacking = [c for c in SCHEMA if c not in rows.columns]
    added = rows.with_columns(pl.lit(None, dtype=SCHEMA[c]).alias(c) for c in lacking)
    before = pl.col("format_version")  # the row's format (not its cell's IDENTITY_VERSION)
    filled = added.with_columns(
        *(pl.when(before < since).then(pl.col(c).fill_null(pl.lit(v, dtype=SCHEMA[c]))).otherwise(pl.col(c)).alias(c)
          for c, (since, v) in ADDED_TO_CELLS.items()),
        *(how.cast(SCHEMA[c]).alias(c) for c, how in DERIVED.items() if c in lacking),
        format_version=pl.lit(FORMAT_VERSION, dtype=pl.Int64),
    )
    return with_policy_ids(filled)


def with_policy_ids(rows: pl.DataFrame) -> pl.DataFrame:
    """`rows` with each null policy_id (or the absent column) computed from the cell the row records (`policy_ids`);
    a table without every cell column is returned as it is."""
    if not set(CELL_COLUMNS) <= set(rows.columns):
        return rows
    if "policy_id" not in rows.columns:
        rows = rows.with_columns(pl.lit(None, dtype=pl.String).alias("policy_id"))
    return rows.with_columns(pl.coalesce("policy_id", policy_ids(rows)).alias("policy_id"))


def policy_ids(rows: pl.DataFrame) -> pl.Series:
    """The policy_id of each row from the cell its columns record (graftcache.fit.plan.Cell.of_row: the camera map
    only where it renames), less the fields IGNORED_BEFORE says its policy ignored. A row of a format that did not
    record its whole cell (before 5) hashes the nulls it holds: it is then a policy of its own."""
    ignored = rows.select(**{name: how.fill_null(False) for name, how in IGNORED_BEFORE.items()})
    out = []
    for fields, drops in zip(rows.select(CELL_COLUMNS).iter_rows(named=True), ignored.iter_rows(named=True),
                             strict=True):
        if fields["camera_map"] is not None and not renames(parse_camera_map(fields["camera_map"])):
            fields["camera_map"] = None
        out.append(make_policy_id({k: v for k, v in fields.items() if not drops.get(k)}))
    return pl.Series("policy_id", out, dtype=pl.String)
