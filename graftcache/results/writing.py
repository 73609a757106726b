"""Leased writes of a results file: any number of processes, on one machine or many sharing a file system, append to
one results file. The file stays one Parquet file (what `--results` names, what `report` and polars read), replaced
whole on each append: the writer holds a lease (graftcache.file_lease: a lock file created with O_EXCL, which holds
on NFS where flock may not) around read -> merge -> write a temporary file -> fsync -> rename, so no append is lost,
and it renames only while it still holds the lease. A rename is atomic, and readers read the file through one open
descriptor, so a reader sees the old table or the new one, never a torn file. Why not one part per writer that
readers merge: every reader of a `.parquet` path (the report, notebooks, users' own polars code) would need to
change, to save a cost paid once per cell (mostly the fsync: benchmarks/bench_results.py, docs/measured.md), which
the cell's minutes of training dwarf.

A results path that is a symbolic link is followed (graftcache.results.reading.target): the file it points to is
replaced, with its lease and claims beside it, and the link stays (replacing the path itself would turn the link into
a regular file).
"""

from __future__ import annotations

import os
import socket
import sys
import time
import uuid
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import Any

import polars as pl

from graftcache.errors import ResultsError
from graftcache.file_lease import FileLease
from graftcache.results.reading import failure_reason, read, refuse_directory, target
from graftcache.results.schema import from_rows, validate
from graftcache.store.lease import lease_seconds

#: A writer waiting this long for a results file's lease says what it waits for and on whom (an append holds it ~20
#: ms; a dead, empty or other machine's lease file is waited on until it is judged stale: graftcache.file_lease).
WAIT_TOLD_S = 1.0


def lock_path(path: str | Path) -> Path:
    """The lease file every writer of `path` holds while it appends: hidden, beside it."""
    path = Path(path)
    return path.with_name(f".{path.name}.lock")


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
    graftcache.rollout.rollouts_file): `new` (validated) replaces the rows of `read_table(path)` that share its `key`
    values, of rows of one key in `new` the last is kept, and a failure is a ResultsError naming the `what`."""
    path = target(path)
    new = new.unique(subset=key, keep="last", maintain_order=True)
    refuse_directory(path)
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
