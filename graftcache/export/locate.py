"""What `graftcache export` checks before anything slow: the row exists, and the cache root holds the row's cache.

Building an export loads torch, lerobot and the base policy; a wrong `--cache` (an empty folder, another root, the
cache folder itself) found only then reads as a missing file inside a cache, after the loading. Here it is one line
naming the root searched and the cache the row needs, from the results table and the root's listing alone.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from graftcache import results
from graftcache.errors import ExportError
from graftcache.store.readthrough import reading_root
from graftcache.store.roots import GROUP_META, LocalRoot


def find_row(path: str | Path, run_id: str) -> dict[str, Any]:
    """The results row of `run_id` in the results file at `path`."""
    table = results.read(path)
    rows = table.filter(table["run_id"] == run_id)
    if rows.height == 0:
        raise ExportError(f"{path}: no row with run_id {run_id}")
    return rows.row(0, named=True)


def check_cache_root(row: dict[str, Any], cache: str | None) -> None:
    """Refuse a `--cache` root that does not hold the row's cache, saying which root was searched."""
    root = reading_root(cache)
    key = row["cache_key"]
    if root.get(f"{key}/{GROUP_META}") is not None:
        return
    itself = isinstance(root, LocalRoot) and (root.path / GROUP_META).is_file()
    what = "is a feature cache itself, not a cache root (pass the folder holding it)" if itself else \
        f"holds no cache {key}"
    raise ExportError(f"run {row['run_id']}: cache root {root} {what}; pass the --cache its fit used (the root "
                      f"holding {key}/)")
