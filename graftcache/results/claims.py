"""What keeps a cell's work when many processes write one results file: the claim a process holds while it computes
a cell (`cell_claim`), so that two fits or sweeps writing one file never compute the same cell, and the rows a file
cannot take (a read-only place, a full disk), kept in their cells' run folders (`keep_row`, `append_or_keep`) and
merged later (`merge`, `graftcache merge-rows`)."""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping, Sequence
from contextlib import suppress
from pathlib import Path
from typing import Any

import polars as pl

from graftcache.errors import ResultsError
from graftcache.file_lease import FileLease
from graftcache.results.reading import read, target
from graftcache.results.same_result import disagreement
from graftcache.results.schema import from_rows, validate
from graftcache.results.writing import append


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


def merge(path: str | Path, kept: Sequence[str | Path], log: Callable[[str], None] = print) -> pl.DataFrame:
    """Append the rows of results files `kept` (rows `keep_row` kept, or another results file) to `path`; a
    run_id already in `path` is replaced, and of one run_id in several of `kept` the last is taken, so merging
    twice (or a file and its copy) changes nothing. Rows of one run_id (in `path` or `kept`) that score apart
    (graftcache.results.same_result: computed on other kernels) are said in one line to `log`. Returns the merged
    rows, one per run_id."""
    tables = [read(k) if Path(k).is_file() else None for k in kept]
    absent = [str(k) for k, t in zip(kept, tables) if t is None]
    if absent:
        raise ResultsError(f"no results file at {', '.join(absent)}")
    incoming = pl.concat(tables)
    rows = incoming.unique(subset="run_id", keep="last", maintain_order=True)
    if not len(rows):
        raise ResultsError(f"no rows in {', '.join(map(str, kept))}")
    had = read(path)
    differ = disagreement(pl.concat([had.filter(pl.col("run_id").is_in(rows["run_id"].implode())), incoming]))
    if differ:
        log(f"{path}: {differ}; the last merged is kept")
    append(path, rows)
    return rows
