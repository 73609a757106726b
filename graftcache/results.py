"""The results table: one row per (cell, seed, control), declared once and validated on every write.

A *cell* is (backbone, policy, encoder cache, suite, objective, hyper-parameters); `run_id` hashes the
cell together with seed and control so a rerun can skip rows it already has.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import polars as pl

from graftcache.errors import GraftcacheError
from graftcache.hashing import sha256_json

SCHEMA: dict[str, pl.DataType] = {
    "run_id": pl.String,
    "backbone": pl.String,            # "smolvla" | "pi05"
    "policy": pl.String,              # hub id, local path or "tiny"
    "policy_sha256": pl.String,
    "encoder": pl.String,             # registry name; native controls: the tower's name, e.g. "smolvla-native"
    "cache_key": pl.String,
    "suite": pl.String,
    "seed": pl.Int64,
    "control": pl.String,             # "none" for the plain graft
    "pool_grid": pl.String,           # e.g. "8x8"
    "objective": pl.String,           # "flow" | "align" | "eval" (native control)
    "steps": pl.Int64,
    "lr": pl.Float64,
    "batch_size": pl.Int64,
    "buffer_mib": pl.Int64,           # shuffle buffer of a flow fit, MiB of features (0: trains nothing / align)
    "train_loss_final": pl.Float64,
    "eval_mse": pl.Float64,           # full chunk, normalised action units
    "eval_mse_first": pl.Float64,     # first action of the chunk, normalised units
    "eval_mse_raw": pl.Float64,       # full chunk, raw action units
    "eval_mse_episodes": pl.List(pl.Float64),  # per held-out episode (episode order), for bootstraps
    "n_eval_frames": pl.Int64,
    "n_eval_episodes": pl.Int64,
    "eval_split_seed": pl.Int64,
    "wall_s": pl.Float64,
    "device": pl.String,
    "compute_dtype": pl.String,       # resolved model compute dtype ("bf16" | "fp32"), never "auto"
    "random_init": pl.Boolean,        # any random-init weights in the encoder or the backbone
    "n_dropped_nonfinite": pl.Int64,  # frames dropped for NaN/inf by `fit --drop-nonfinite` (0: none): the suite's
                                      # with NaN/inf state or action chunk, plus those whose features the cell read
                                      # and found NaN/inf (features are checked as they stream)
    "numerics_drift": pl.Float64,     # largest numerics-probe difference / its RMS over the cell's caches, as
                                      # recomputed by this environment (encoders/fingerprint.py); null: unchecked
    "camera_map": pl.String,          # which cache camera fed each policy camera, e.g. "image=agentview,image2=
                                      # eye_in_hand" (graftcache/cameras.py); also when every name matched
    "graftcache_version": pl.String,
    "command": pl.String,             # the command line that produced the row
}

CONTROLS_NATIVE = ("native",)

# Columns added to SCHEMA after results files were first written: reading an older file adds them as nulls, so
# its cells are still skipped and new rows can still be appended to it.
ADDED_COLUMNS = ("numerics_drift", "buffer_mib", "camera_map")

# What a report needs of a table: enough to place every MSE in the (backbone, suite, encoder, control, seed)
# grid. Tables from older versions, other tools or a paper need only these (conform fills the other SCHEMA
# columns with nulls; without eval_mse_episodes the report's bootstrap resamples seeds only). Writing rows
# (validate, append) still demands every SCHEMA column.
REPORT_COLUMNS = ("backbone", "suite", "encoder", "control", "seed", "eval_mse")


def empty() -> pl.DataFrame:
    """An empty results table with the declared schema."""
    return pl.DataFrame(schema=SCHEMA)


def make_run_id(cell: Mapping[str, Any]) -> str:
    """Stable id of a cell + seed + control: sha256 of its canonical JSON, 16 hex chars."""
    return sha256_json(dict(cell))[:16]


def validate(rows: pl.DataFrame) -> pl.DataFrame:
    """Return `rows` cast to SCHEMA; raise naming the missing/extra columns or null run_ids."""
    missing = [c for c in SCHEMA if c not in rows.columns]
    extra = [c for c in rows.columns if c not in SCHEMA]
    if missing or extra:
        raise GraftcacheError(f"results rows do not match the schema: missing {missing}, unexpected {extra}")
    out = rows.select([pl.col(c).cast(t, strict=True) for c, t in SCHEMA.items()])
    if out["run_id"].null_count():
        raise GraftcacheError("results rows with a null run_id")
    return out


def conform(rows: pl.DataFrame) -> pl.DataFrame:
    """The lenient reading of a table for analysis: REPORT_COLUMNS required (and their keys non-null),
    absent SCHEMA columns added as nulls, columns outside SCHEMA dropped, everything cast to SCHEMA."""
    missing = [c for c in REPORT_COLUMNS if c not in rows.columns]
    if missing:
        raise GraftcacheError(
            f"results table lacks column(s) {', '.join(missing)} (a report needs {', '.join(REPORT_COLUMNS)})"
        )
    columns = []
    for name, dtype in SCHEMA.items():
        if name not in rows.columns:
            columns.append(pl.repeat(None, len(rows), dtype=dtype, eager=True).alias(name))
            continue
        try:
            columns.append(rows[name].cast(dtype, strict=True))
        except pl.exceptions.PolarsError:
            raise GraftcacheError(f"column {name} ({rows[name].dtype}) cannot be read as {dtype}") from None
    out = pl.DataFrame(columns)
    keys = [c for c in REPORT_COLUMNS if c != "eval_mse" and out[c].null_count()]
    if keys:
        raise GraftcacheError(f"null values in key column(s) {', '.join(keys)}")
    return out


def read(path: str | Path) -> pl.DataFrame:
    """Read a results Parquet file (an absent file is an empty table)."""
    path = Path(path)
    if not path.exists():
        return empty()
    try:
        rows = pl.read_parquet(path)
        older = [pl.lit(None, dtype=SCHEMA[c]).alias(c) for c in ADDED_COLUMNS if c not in rows.columns]
        return validate(rows.with_columns(older))
    except GraftcacheError as e:
        raise GraftcacheError(f"{path}: {e}") from None
    except (pl.exceptions.PolarsError, OSError) as e:
        reason = "empty file" if not path.stat().st_size else (str(e).splitlines() or [type(e).__name__])[0]
        raise GraftcacheError(f"{path}: not a Parquet results table ({reason}); pass another --results") from None


def read_for_report(path: str | Path) -> pl.DataFrame:
    """Read any results table a report can use (see REPORT_COLUMNS), conformed to SCHEMA.

    Unlike `read`, nothing here is silent: an absent, empty or non-Parquet file, a table without rows and
    one lacking a needed column are GraftcacheErrors naming the file, since a report of nothing must not
    look like a report.
    """
    path = Path(path)
    if not path.is_file():
        raise GraftcacheError(f"{path}: no results file (run `graftcache sweep` or `graftcache demo` first)")
    try:
        rows = pl.read_parquet(path)
    except (pl.exceptions.PolarsError, OSError) as e:
        reason = "empty file" if not path.stat().st_size else (str(e).splitlines() or [type(e).__name__])[0]
        raise GraftcacheError(f"{path}: not a Parquet results table ({reason})") from None
    try:
        table = conform(rows)
    except GraftcacheError as e:
        raise GraftcacheError(f"{path}: {e}") from None
    if not len(table):
        raise GraftcacheError(f"{path}: no rows")
    return table


def done_run_ids(path: str | Path) -> set[str]:
    """run_ids already present in a results file: those cells are skipped on rerun."""
    return set(read(path)["run_id"].to_list())


def append(path: str | Path, rows: Iterable[Mapping[str, Any]] | pl.DataFrame) -> pl.DataFrame:
    """Validate `rows` and append them to the Parquet file atomically (write temp, then rename).

    A row whose run_id is already present replaces the old one, so a file never holds duplicates.
    """
    path = Path(path)
    new = validate(rows if isinstance(rows, pl.DataFrame) else pl.DataFrame(list(rows), schema=SCHEMA))
    old = read(path)
    table = pl.concat([old.filter(~pl.col("run_id").is_in(new["run_id"].implode())), new])
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    table.write_parquet(tmp)
    os.replace(tmp, path)
    return table
