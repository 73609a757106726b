"""Reading results files: one open descriptor a file (a writer may replace it meanwhile), through the upgrade path
(`read`, strict: what a fit skips by and appends to), or conformed for a report (`read_for_report`: any table with
REPORT_COLUMNS)."""

from __future__ import annotations

import errno
import io
import os
from pathlib import Path

import polars as pl

from graftcache.errors import GraftcacheError, ResultsError, first_line
from graftcache.results.schema import conform, empty, validate
from graftcache.results.upgrade import upgrade, with_policy_ids


def refuse_directory(path: Path) -> None:
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
    refuse_directory(path)
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
    return first_line(e)


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
        table = conform(with_policy_ids(rows))
    except GraftcacheError as e:
        raise GraftcacheError(f"{path}: {e}") from None
    if not len(table):
        raise GraftcacheError(f"{path}: no rows")
    return table


def done_run_ids(path: str | Path) -> set[str]:
    """run_ids already present in a results file: those cells are skipped on rerun."""
    return set(read(path)["run_id"].to_list())
