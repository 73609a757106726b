"""What a results row is: its columns (SCHEMA), the format of rows (FORMAT_VERSION), the version of what their
run_ids hash (IDENTITY_VERSION), and how a table is checked against them (`validate` on every write, `conform` for a
report). A *cell* is (backbone, policy, encoder cache, suite, seed, control, objective, hyper-parameters): one fit,
one row; `run_id` hashes it (graftcache.fit.plan.Cell) so a rerun can skip rows it already has. How rows of older
formats become rows of this one: graftcache.results.upgrade.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Any

import polars as pl

from graftcache.codecs import without_none
from graftcache.errors import GraftcacheError
from graftcache.hashing import sha256_json
from graftcache.requests import FitRequest
from graftcache.settings import declared

#: The version of what a cell's run_id hashes (graftcache.fit.plan.Cell.run_id): hashed into every run_id under the
#: key `format_version`, the name cells of results format 3 gave it, so rows of formats IDENTITY_VERSION..FORMAT_VERSION
#: name the same cell by the same run_id and a rerun skips what any of them holds. A Cell is no format on disk of its
#: own (rows and run folders record its fields), so this is the version of its identity, not of a format.
IDENTITY_VERSION = 3
#: Each FitRequest setting added to cells since IDENTITY_VERSION (its declaration's graftcache.settings.Identity
#: `since`) -> (the results format that added it, what every cell before it held). Such a setting is hashed only off
#: that value (graftcache.fit.plan.Cell.run_id), so earlier cells keep their run_ids, and graftcache.results.upgrade
#: fills its column in earlier rows with it: `eval_split` (format 4), every earlier cell split the
#: graftcache way.
ADDED_TO_CELLS: dict[str, tuple[int, Any]] = {
    name: (d.setting.cell.since, d.setting.cell.before) for name, d in declared(FitRequest).items()
    if d.setting.cell is not None and d.setting.cell.since is not None}
#: Every field of a cell (graftcache.fit.plan.Cell), each a column: what a Plan resolves, the FitRequest settings
#: declared into cells, the camera map. A row written without a policy_id gets one from them
#: (graftcache.results.upgrade).
CELL_COLUMNS: tuple[str, ...] = ("policy", "cache_key", "seed", "control", "pool_grid", "objective",
                                 *(name for name, d in declared(FitRequest).items() if d.setting.cell is not None),
                                 "camera_map")
#: The version of what a policy_id hashes (make_policy_id).
POLICY_IDENTITY_VERSION = 1
#: What cells of identity version 3 held in each field added since (ADDED_TO_CELLS).
IDENTITY_3_VALUES: dict[str, Any] = {name: before for name, (_, before) in ADDED_TO_CELLS.items()}
#: The format of results rows. Files of an older format go through graftcache.results.upgrade, the one place that
#: knows them. Format 3 (one word per idea) renamed no column but changed what cells hold (`pool_grid` is
#: the resolved grid, never "native"), hence every run_id. Format 4 added columns and one cell field,
#: `eval_split`, hashed only off its default, so its cells hash as format 3's: format 3 rows are upgraded. Format 5
#: added a column for each cell field rows lacked (`eval_fraction`, `eval_frames`, `num_denoise_steps`,
#: `lora_rank`), so that a row records the whole cell its run_id hashes (graftcache.fit.plan.Cell.of_row); its
#: run_ids are format 4's. Format 6 added `policy_id` (`make_policy_id`): its run_ids are
#: format 5's. Format 7 added `kernels` (what a row's numbers depend on beyond its cell: rows of one run_id computed on
#: other kernels differ, graftcache.results.same_result): its run_ids are format 6's, and an older row's kernels are
#: unknown (null). A setting declared into cells by a later format (ADDED_TO_CELLS) makes that format this one.
FORMAT_VERSION = max(7, *(since for since, _ in ADDED_TO_CELLS.values()))

#: A setting's column type, by its field's type.
_POLARS: dict[type, pl.DataType] = {int: pl.Int64, float: pl.Float64, str: pl.String, bool: pl.Boolean}

SCHEMA: dict[str, pl.DataType] = {
    "run_id": pl.String,
    "policy_id": pl.String,           # the policy's function (make_policy_id): rows of one policy_id are one policy,
                                      # scored on the same frames (a sweep copies such a row instead of refitting it)
    "format_version": pl.Int64,       # FORMAT_VERSION of the row (what its run_id hashes: IDENTITY_VERSION)
    "backbone": pl.String,            # a graftcache.backbone_registry.BACKBONES name, e.g. "smolvla"
    "backbone_params": pl.Int64,      # parameters of the policy as loaded (before the graft): the analysis
                                      # orders backbones by it (graftcache/analysis/ladder.py)
    "policy": pl.String,              # hub id, local path or "tiny"
    "policy_sha256": pl.String,
    "encoder": pl.String,             # registry name; native controls: the tower's name, e.g. "smolvla-native"
    "cache_key": pl.String,
    "suite": pl.String,
    "seed": pl.Int64,
    "control": pl.String,             # "none" for the plain graft
    "pool_grid": pl.String,           # e.g. "8x8"
    "objective": pl.String,           # "flow" | "align" | "align-flow" | "eval" (native control)
    # then every FitRequest setting declared a column (graftcache/requests.py: `column=True`), in declaration
    # order, typed from its field: steps, lr, batch_size, buffer_mib, eval_fraction, eval_split_seed, eval_split,
    # eval_frames, eval_batch_size, num_denoise_steps, lora_rank (the cell's: 0 but for the lora control),
    # compute_dtype (resolved: "bf16" | "fp32", never "auto"), command (the command line that produced the row);
    # every cell field is a column (tests/test_previous_formats.py checks it)
    **{name: _POLARS[without_none(d.hint)] for name, d in declared(FitRequest).items() if d.setting.column},
    "train_loss_final": pl.Float64,
    "eval_mse": pl.Float64,           # full chunk, normalised action units
    "eval_mse_first": pl.Float64,     # first action of the chunk, normalised units
    "eval_mse_raw": pl.Float64,       # full chunk, raw action units
    "eval_mse_episodes": pl.List(pl.Float64),  # per held-out episode (episode order), for bootstraps
    "eval_ci_mse": pl.Float64,        # critical-interval MSE (graftcache/critical.py), normalised units; null:
                                      # no scored chunk reached a critical step
    "eval_ci_mse_episodes": pl.List(pl.Float64),  # CI-MSE per held-out episode, in eval_mse_episodes' order
                                      # (null for an episode without a critical step)
    "n_eval_frames": pl.Int64,
    "n_eval_episodes": pl.Int64,
    "eval_mse_arm": pl.Float64,       # eval_mse over the first action_dim - 1 dims (LIBERO: the 6-d end-effector
                                      # delta), normalised units; null: 1-d actions, or a row of format 3
    "eval_mse_gripper": pl.Float64,   # eval_mse over the last action dim (LIBERO: the gripper), normalised units;
                                      # per frame eval_mse = ((A - 1) * arm + gripper) / A; null: a format 3 row
    "wall_s": pl.Float64,             # a cell trained in a pass of several: its share (the pass's wall time / cells)
    "cells_per_pass": pl.Int64,       # cells trained in the backbone pass that produced the row (1: alone)
    "device": pl.String,
    "random_init": pl.Boolean,        # any random-init weights: encoder_random_init or backbone_random_init
    "encoder_random_init": pl.Boolean,  # the cache's encoder weights were random-init (its manifest's random_init;
                                      # a native tower's cache: the policy's tower, so a tiny policy's says True)
    "backbone_random_init": pl.Boolean,  # the policy was random-init or trained by train-tiny, not released weights
    "n_dropped_nonfinite": pl.Int64,  # frames dropped for NaN/inf by `fit --drop-nonfinite` (0: none): the suite's
                                      # with NaN/inf state or action chunk, plus those whose features the cell read
                                      # and found NaN/inf (features are checked as they stream)
    "numerics_drift": pl.Float64,     # largest numerics-probe difference / its RMS over the cell's caches, as
                                      # recomputed by this environment (encoders/fingerprint.py); null: unchecked
    "camera_map": pl.String,          # which cache camera fed each policy camera, e.g. "image=agentview,image2=
                                      # eye_in_hand" (graftcache/cameras.py); also when every name matched
    "graftcache_version": pl.String,
    "activation_checkpointing": pl.String,  # the recompute plan "off" | "mlp" | "on" that `--recompute` (auto)
                                      # resolved to (graftcache.requests.RECOMPUTE_PLANS)
    "eval_seconds_per_frame": pl.Float64,  # scoring's wall time (reading, prefix, denoising) / n_eval_frames
    "attention": pl.String,           # "eager" | "sdpa": what `--attention` (auto) resolved to for the frozen LM and
                                      # expert (graftcache/backbones/attention.py); null: a row written before it
    "kernels": pl.String,             # the kernels that computed the row (graftcache.runtime.kernels), e.g.
                                      # "cpu:avx512+amx": rows of one run_id and compute_dtype on equal kernels are
                                      # equal whatever the thread count; null: a row of format 6 or older
}

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


def make_policy_id(fields: Mapping[str, Any]) -> str:
    """Stable id of a policy as rolled out and scored, 16 hex chars like a run_id: the sha256 of what decides its
    function and its scores (a cell's fields, less those its control's policy ignores, with what stands in for them:
    graftcache.fit.plan.Plan.policy_id), under POLICY_IDENTITY_VERSION, so that it never equals a run_id by accident."""
    return sha256_json({**fields, "policy_identity": POLICY_IDENTITY_VERSION})[:16]


def validate(rows: pl.DataFrame) -> pl.DataFrame:
    """Return `rows` cast to SCHEMA; raise naming the missing/extra columns or null run_ids."""
    missing = [c for c in SCHEMA if c not in rows.columns]
    extra = [c for c in rows.columns if c not in SCHEMA]
    if missing or extra:
        raise GraftcacheError(f"results rows do not match the schema: missing {missing}, unexpected {extra}")
    out = pl.DataFrame([cast_exactly(rows[c], t) for c, t in SCHEMA.items()])
    if out["run_id"].null_count():
        raise GraftcacheError("results rows with a null run_id")
    return out


def from_rows(rows: Iterable[Mapping[str, Any]]) -> pl.DataFrame:
    """Rows (dicts; an absent key is a null) as a table of the types their values have, for `validate` to check:
    building it with `schema=SCHEMA` would silently truncate a float seed."""
    dicts = [dict(r) for r in rows]
    if not dicts:
        return empty()
    table = pl.DataFrame(dicts, infer_schema_length=None)
    return table.with_columns(pl.lit(None, dtype=t).alias(c) for c, t in SCHEMA.items() if c not in table.columns)


def cast_exactly(column: pl.Series, dtype: pl.DataType) -> pl.Series:
    """`column` as `dtype`, refused (naming the column and a value) when that would change a value: polars'
    strict cast still truncates a float seed 0.5 to 0, which a rewrite would then make permanent."""
    try:
        out = column.cast(dtype, strict=True)
    except pl.exceptions.PolarsError:
        raise GraftcacheError(f"column {column.name} ({column.dtype}) cannot be read as {dtype}") from None
    if column.dtype != dtype and column.dtype.is_numeric() and dtype.is_numeric():
        changed = (out.cast(column.dtype) != column).fill_null(False)
        if changed.any():
            value = column.filter(changed)[0]
            raise GraftcacheError(f"column {column.name} holds {value!r}, which {dtype} cannot hold unchanged "
                                  f"({int(changed.sum())} such value(s)); fix the table, graftcache will not round it")
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
        columns.append(cast_exactly(rows[name], dtype))
    out = pl.DataFrame(columns)
    keys = [c for c in REPORT_COLUMNS if c != "eval_mse" and out[c].null_count()]
    if keys:
        raise GraftcacheError(f"null values in key column(s) {', '.join(keys)}")
    return out
