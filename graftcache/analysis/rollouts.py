"""What the report reads of a rollouts file: each episode's `run_id` (the results row whose policy ran it) and
`success`. Every other column (suite, task_index, episode, seed, steps, seconds, ...) is provenance the report
does not need, so episodes a user ran with other tools join as well as those `graftcache rollout` writes.

An episode whose run_id is not in the results table is refused (one line naming the file and such a run_id), never
dropped: rollouts of another results file would otherwise leave the report silently about fewer cells.
"""

from __future__ import annotations

from pathlib import Path

import polars as pl

from graftcache.errors import GraftcacheError

ROLLOUT_COLUMNS = ("run_id", "success")


def _success(column: pl.Series, path: Path) -> pl.Series:
    """`success` as booleans: booleans as they are, integers only when every one is 0 or 1."""
    if column.dtype == pl.Boolean:
        return column
    if column.dtype.is_integer() and column.is_in([0, 1]).all():
        return column.cast(pl.Boolean)
    odd = column.filter(~column.is_in([0, 1])) if column.dtype.is_numeric() else column
    raise GraftcacheError(f"{path}: column success holds {column.dtype} values such as {odd[0]!r}, not true/false")


def read_rollouts(path: str | Path, results: pl.DataFrame) -> pl.DataFrame:
    """The rollouts Parquet file at `path` as (run_id, success) per episode, checked against `results`' run_ids;
    anything unusable is a GraftcacheError naming the file."""
    path = Path(path)
    if not path.is_file():
        raise GraftcacheError(f"{path}: no rollouts file")
    try:
        table = pl.read_parquet(path)
    except (pl.exceptions.PolarsError, OSError) as e:
        reason = (str(e).strip().splitlines() or [type(e).__name__])[0]
        raise GraftcacheError(f"{path}: not a Parquet rollouts table ({reason})") from None
    missing = [c for c in ROLLOUT_COLUMNS if c not in table.columns]
    if missing:
        raise GraftcacheError(f"{path}: rollouts table lacks column(s) {', '.join(missing)} (the report needs "
                              f"{', '.join(ROLLOUT_COLUMNS)} per episode)")
    if not len(table):
        raise GraftcacheError(f"{path}: no rollouts (no rows)")
    nulls = [c for c in ROLLOUT_COLUMNS if table[c].null_count()]
    if nulls:
        raise GraftcacheError(f"{path}: null values in column(s) {', '.join(nulls)}")
    rollouts = pl.DataFrame([table["run_id"].cast(pl.String), _success(table["success"], path)])
    unknown = rollouts.filter(~pl.col("run_id").is_in(results["run_id"].implode()))["run_id"].unique(
        maintain_order=True)
    if len(unknown):
        raise GraftcacheError(f"{path}: {len(unknown)} run_id(s) not in the results table, e.g. {unknown[0]}: pass "
                              "the results file whose rows were rolled out")
    return rollouts
