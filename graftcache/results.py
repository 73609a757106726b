"""The results table: one row per cell, declared once and validated on every write.

A *cell* is (backbone, policy, encoder cache, suite, seed, control, objective, hyper-parameters): one fit, one
row; `run_id` hashes it (graftcache.fit.plan.Cell) so a rerun can skip rows it already has.

Any number of processes, on one machine or many sharing a file system, append to one results file. The file
stays one Parquet file (what `--results` names, what `report` and polars read), replaced whole on each append:
the writer holds a lease (graftcache.file_lease: a lock file created with O_EXCL, which holds on NFS where
flock may not) around read -> merge -> write a temporary file -> fsync -> rename, so no append is lost, and
it renames only while it still holds the lease. A rename is atomic, and readers read the file through one
open descriptor, so a reader sees the old table or the new one, never a torn file. Why not one part per
writer that readers merge: every reader of a `.parquet` path (the report, notebooks, users' own polars code)
would need to change, to save a cost paid once per cell (22 ms a row at 10k rows on 2 AMD EPYC cores, most of
it the fsync: benchmarks/bench_results.py), which the cell's minutes of training dwarf.

A row that cannot be written (a read-only place, a full disk) is kept in its cell's run folder
(`keep_row`) and merged later with `merge` (`graftcache merge-rows`). `cell_claim` is the lease a process
holds while it computes a cell, so that two fits or sweeps writing one file never compute the same cell.

A results path that is a symbolic link is followed (`target`): the file it points to is replaced, with its lease
and claims beside it, and the link stays (replacing the path itself would turn the link into a regular file).
"""

from __future__ import annotations

import errno
import io
import os
import socket
import sys
import time
import uuid
from collections.abc import Callable, Iterable, Mapping, Sequence
from contextlib import suppress
from pathlib import Path
from typing import Any

import polars as pl

import graftcache
from graftcache.codecs import without_none
from graftcache.errors import GraftcacheError, ResultsError
from graftcache.file_lease import FileLease
from graftcache.hashing import sha256_json
from graftcache.requests import FitRequest
from graftcache.settings import declared
from graftcache.store.lease import lease_seconds

#: A writer waiting this long for a results file's lease says what it waits for and on whom (an append holds it ~20
#: ms; a dead, empty or other machine's lease file is waited on until it is judged stale: graftcache.file_lease).
WAIT_TOLD_S = 1.0

#: The shape of the cells run_ids hash (graftcache.fit.plan.Cell, whose `format_version` field holds it): rows of
#: formats CELL_FORMAT..FORMAT_VERSION name the same cell by the same run_id, so a rerun skips what any of them holds.
CELL_FORMAT = 3
#: Each FitRequest setting added to cells since CELL_FORMAT (its declaration's graftcache.settings.Identity `since`)
#: -> (the results format that added it, what every cell before it held). Such a setting is hashed only off that
#: value (graftcache.fit.plan.Cell.run_id), so earlier cells keep their run_ids, and `upgrade` fills its column in
#: earlier rows with it: `eval_split` (format 4, issue 31), every earlier cell split the graftcache way.
ADDED_TO_CELLS: dict[str, tuple[int, Any]] = {
    name: (d.setting.cell.since, d.setting.cell.before) for name, d in declared(FitRequest).items()
    if d.setting.cell is not None and d.setting.cell.since is not None}
#: What cells of format 3 held in each field added since (ADDED_TO_CELLS).
FORMAT_3_VALUES: dict[str, Any] = {name: before for name, (_, before) in ADDED_TO_CELLS.items()}
#: The format of results rows. Files of an older format go through `upgrade`, the one place that knows them. Format 3
#: (issue 23, one word per idea) renamed no column but changed what cells hold (`pool_grid` is the resolved grid,
#: never "native"), hence every run_id. Format 4 (issue 31) added columns and one cell field, `eval_split`, hashed
#: only off its default, so its cells hash as format 3's: format 3 rows are upgraded. A setting declared into cells
#: by a later format (ADDED_TO_CELLS) makes that format this one.
FORMAT_VERSION = max(4, *(since for since, _ in ADDED_TO_CELLS.values()))
#: What a row without a column of format 4 (of format 3, or of format 4 written before issue 32 split random_init)
#: held in it, where its other columns say so: random_init is the union of the encoder's and the backbone's, so a
#: row whose random_init is false had neither; a true one leaves both unknown (null).
DERIVED: dict[str, pl.Expr] = {
    "encoder_random_init": pl.when(~pl.col("random_init")).then(False),
    "backbone_random_init": pl.when(~pl.col("random_init")).then(False),
}

#: A setting's column type, by its field's type.
_POLARS: dict[type, pl.DataType] = {int: pl.Int64, float: pl.Float64, str: pl.String, bool: pl.Boolean}

SCHEMA: dict[str, pl.DataType] = {
    "run_id": pl.String,
    "format_version": pl.Int64,       # FORMAT_VERSION of the row (the cell its run_id hashes: CELL_FORMAT)
    "backbone": pl.String,            # a graftcache.backbone_table.BACKBONES name, e.g. "smolvla"
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
    # order, typed from its field: steps, lr, batch_size, buffer_mib, eval_split_seed, eval_split, eval_batch_size,
    # compute_dtype (resolved: "bf16" | "fp32", never "auto"), command (the command line that produced the row)
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
    "activation_checkpointing": pl.String,  # the memory plan "off" | "mlp" | "on" (graftcache.requests.MEMORY_PLANS)
                                      # what `--activation-checkpointing` (auto) resolved to
    "eval_seconds_per_frame": pl.Float64,  # scoring's wall time (reading, prefix, denoising) / n_eval_frames
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


def _refuse_directory(path: Path) -> None:
    if path.is_dir():
        raise ResultsError(f"{path}: is a directory, not a results file; pass a .parquet file")


def target(path: str | Path) -> Path:
    """The file a results path names: a symbolic link followed (see the module docstring)."""
    path = Path(path)
    return Path(os.path.realpath(path)) if path.is_symlink() else path


def load_table(path: Path) -> pl.DataFrame:
    """The Parquet table at `path`, read through one open descriptor: polars opening the path again (footer,
    then row groups) could read two files when a writer replaces it in between. A stale NFS handle (the file
    replaced on the server as we read it) is read again."""
    _refuse_directory(path)
    for attempt in range(5):
        try:
            with open(path, "rb") as f:
                data = f.read()
            break
        except OSError as e:
            if e.errno != errno.ESTALE or attempt == 4:
                raise
    return pl.read_parquet(io.BytesIO(data))


def failure_reason(e: BaseException, path: Path) -> str:
    """An OSError or polars error as a few words (polars' OSErrors carry no errno, only their text)."""
    if isinstance(e, OSError) and e.strerror:
        return e.strerror
    if path.is_file() and not path.stat().st_size:
        return "empty file"
    return (str(e).strip().splitlines() or [type(e).__name__])[0]


def read(path: str | Path) -> pl.DataFrame:
    """Read a results Parquet file (an absent file is an empty table)."""
    path = Path(path)
    if not path.exists():
        return empty()
    try:
        return validate(upgrade(load_table(path), path))
    except ResultsError:
        raise
    except GraftcacheError as e:
        raise ResultsError(f"{path}: {e}") from None
    except (pl.exceptions.PolarsError, OSError) as e:
        raise ResultsError(f"{path}: not a Parquet results table ({failure_reason(e, path)}); "
                           "pass another --results") from None


def upgrade(rows: pl.DataFrame, path: Path) -> pl.DataFrame:
    """The one upgrade path for results files: rows of this format as they are; rows of format 3 (their run_ids
    hash cells as this format's do: CELL_FORMAT), and rows of format 4 written before it gained a column, with the
    columns they lack, each holding ADDED_TO_CELLS' value, what DERIVED derives from the row, or null; rows of an
    older format (format 1 had no format_version column; format 2 hashed `pool_grid="native"` and the format
    version 2 into its run_ids) are refused in one line with the commands
    that rebuild them, since their run_ids hash cells of another shape: a rerun could not skip their cells and
    would write each twice. Rows of a newer format (a later graftcache wrote them) and tables that are no
    graftcache results at all (no run_id or report column) are refused as such."""
    current = "format_version" in rows.columns and rows["format_version"].eq(FORMAT_VERSION).all()
    if current and set(SCHEMA) <= set(rows.columns):
        return rows
    if "format_version" in rows.columns and rows["format_version"].is_in(range(CELL_FORMAT, FORMAT_VERSION + 1)).all():
        return _from_format_3(rows)
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
    old = rows if "format_version" not in rows.columns else rows.filter(pl.col("format_version") < CELL_FORMAT)
    recorded = old["command"].drop_nulls().unique(maintain_order=True).to_list() if "command" in old.columns else []
    commands = [c for c in recorded if c.startswith("graftcache ")]  # graftcache < issue 29 recorded `fit` alone
    rebuild = f"`{commands[0]}`" if commands else "the fits or sweeps that wrote them (its rows record no command line)"
    more = f" (and {len(commands) - 1} other command(s) its rows record)" if len(commands) > 1 else ""
    raise ResultsError(f"{path}: {old.height} row(s) of an older results format than {CELL_FORMAT} (run_ids "
                       f"of cells of another shape); move the file aside and rebuild it: {rebuild}{more}")


def _from_format_3(rows: pl.DataFrame) -> pl.DataFrame:
    """Rows of formats CELL_FORMAT..FORMAT_VERSION as this format: the columns they lack added, null but where
    ADDED_TO_CELLS knows what rows of a format before a cell field's held (also filled on such rows of a table that
    has the column) or DERIVED derives it."""
    lacking = [c for c in SCHEMA if c not in rows.columns]
    added = rows.with_columns(pl.lit(None, dtype=SCHEMA[c]).alias(c) for c in lacking)
    before = pl.col("format_version")  # the row's format (not the cells' CELL_FORMAT)
    return added.with_columns(
        *(pl.when(before < since).then(pl.col(c).fill_null(pl.lit(v, dtype=SCHEMA[c]))).otherwise(pl.col(c)).alias(c)
          for c, (since, v) in ADDED_TO_CELLS.items()),
        *(how.cast(SCHEMA[c]).alias(c) for c, how in DERIVED.items() if c in lacking),
        format_version=pl.lit(FORMAT_VERSION, dtype=pl.Int64),
    )


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
        rows = load_table(path)
    except (pl.exceptions.PolarsError, OSError) as e:
        raise ResultsError(f"{path}: not a Parquet results table ({failure_reason(e, path)})") from None
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


def lock_path(path: str | Path) -> Path:
    """The lease file every writer of `path` holds while it appends: hidden, beside it."""
    path = Path(path)
    return path.with_name(f".{path.name}.lock")


def claims_folder(path: str | Path) -> Path:
    """Where the cell claims of the results file `path` are: a hidden folder beside it, removed once empty."""
    path = target(path)
    return path.with_name(f".{path.name}.claims")


def cell_claim(path: str | Path, run_id: str) -> FileLease:
    """The lease a process holds while it computes the cell `run_id` whose row goes to `path`."""
    return FileLease(claims_folder(path) / f"{run_id}.claim")


def drop_claims_folder(path: str | Path) -> None:
    """Remove the claims folder of `path` if no claim is left in it (another process's claims keep it)."""
    with suppress(OSError):
        claims_folder(path).rmdir()


def _to_stderr(line: str) -> None:
    print(f"graftcache: {line}", file=sys.stderr)


def fsync(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _publish(path: Path, table: pl.DataFrame, lease: FileLease) -> bool:
    """Write `table` to a temporary file beside `path`, make it durable, and rename it over `path` if `lease` is
    still ours (False: it was taken over, nothing changed). The temporary file never outlives the call."""
    tmp = path.with_name(f".{path.name}.{socket.gethostname()}.{os.getpid()}.{uuid.uuid4().hex[:8]}.tmp")
    try:
        table.write_parquet(tmp)
        fsync(tmp)
        if not lease.holds():
            return False
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    try:  # the rename itself survives a crash once its folder is synced
        fsync(path.parent)
    except OSError:
        pass  # a file system that cannot sync folders: the rename is still atomic
    return True


def append(path: str | Path, rows: Iterable[Mapping[str, Any]] | pl.DataFrame,
           log: Callable[[str], None] = _to_stderr) -> pl.DataFrame:
    """Validate `rows` and append them to the Parquet file under its writers' lease (see the module docstring).

    A row whose run_id is already present replaces the old one, and of rows of one run_id among `rows` the last
    is kept, so a file never holds duplicates (appending a table twice changes nothing). Anything that stops the
    file being written is a ResultsError naming it; the file is then unchanged. A wait for the lease longer than
    WAIT_TOLD_S is said once through `log`, naming the lock and its holder.
    """
    new = validate(rows if isinstance(rows, pl.DataFrame) else from_rows(rows))
    return append_table(path, new, read, key="run_id", log=log)


def append_table(path: str | Path, new: pl.DataFrame, read_table: Callable[[Path], pl.DataFrame], *, key: str,
                 log: Callable[[str], None] = _to_stderr, what: str = "results file") -> pl.DataFrame:
    """`append`'s lease -> read -> merge -> publish loop for any table kept this way (the rollouts file too,
    graftcache.rollout.table): `new` (validated) replaces the rows of `read_table(path)` that share its `key`
    values, of rows of one key in `new` the last is kept, and a failure is a ResultsError naming the `what`."""
    path = target(path)
    new = new.unique(subset=key, keep="last", maintain_order=True)
    _refuse_directory(path)
    lock = lock_path(path)
    if lock.is_dir():
        raise ResultsError(f"{lock}: is a directory, where the writers of {path} keep their lock file; remove it")
    while True:
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            lease = FileLease(lock)
            lease.acquire(on_wait=lambda holder: log(
                f"waiting for {lock} (the lock of {path}), held by {holder}; a holder that is dead, or silent for "
                f"{lease_seconds():g} s, is taken over"), patience=WAIT_TOLD_S)
            try:
                old = read_table(path)
                table = pl.concat([old.filter(~pl.col(key).is_in(new[key].implode())), new])
                if _publish(path, table, lease):
                    return table
            finally:
                lease.release()
        except (OSError, pl.exceptions.PolarsError) as e:
            raise ResultsError(f"{path}: cannot write the {what} ({failure_reason(e, path)})") from None
        time.sleep(0.1)  # presumed dead and taken over while writing: read the successor's table and retry


def keep_row(folder: str | Path, row: Mapping[str, Any]) -> Path:
    """Keep a row that could not be appended as `folder`/row.parquet (a one-row results file), for `merge`."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    kept = folder / "row.parquet"
    tmp = folder / f".row.{os.getpid()}.tmp"
    try:
        validate(from_rows([row])).write_parquet(tmp)
        os.replace(tmp, kept)
    finally:
        tmp.unlink(missing_ok=True)
    return kept


def append_or_keep(path: str | Path, rows: Sequence[tuple[Mapping[str, Any], str | Path]]) -> None:
    """Append finished cells' rows, each given with its cell's run folder, to `path` at once. Rows the results file
    cannot take are kept, every one, in their run folders (`keep_row`), and one ResultsError says where they are
    and how to merge them: the cells are done, and a pass of several must not lose the rows after the first."""
    try:
        append(path, [row for row, _ in rows])
    except ResultsError as e:
        kept, lost = [], []
        for row, folder in rows:
            try:
                kept.append((row["run_id"], keep_row(folder, row)))
            except OSError as k:
                lost.append(f"the row of cell {row['run_id']} could not be kept either ({k.strerror or k})")
        where = []
        if kept:
            ids, files = ", ".join(i for i, _ in kept), " ".join(str(f) for _, f in kept)
            one = len(kept) == 1
            where.append(f"the row{'' if one else 's'} of cell{'' if one else 's'} {ids} {'is' if one else 'are'} "
                         f"kept in {', '.join(str(f) for _, f in kept)}: once {path} can be written, merge "
                         f"{'it' if one else 'them'} with `graftcache merge-rows {files} --results {path}`")
        raise ResultsError("; ".join([str(e), *lost, *where])) from None


def merge(path: str | Path, kept: Sequence[str | Path]) -> pl.DataFrame:
    """Append the rows of results files `kept` (rows `keep_row` kept, or another results file) to `path`; a
    run_id already in `path` is replaced, and of one run_id in several of `kept` the last is taken, so merging
    twice (or a file and its copy) changes nothing. Returns the merged rows, one per run_id."""
    tables = [read(k) if Path(k).is_file() else None for k in kept]
    absent = [str(k) for k, t in zip(kept, tables) if t is None]
    if absent:
        raise ResultsError(f"no results file at {', '.join(absent)}")
    rows = pl.concat(tables).unique(subset="run_id", keep="last", maintain_order=True)
    if not len(rows):
        raise ResultsError(f"no rows in {', '.join(map(str, kept))}")
    append(path, rows)
    return rows
