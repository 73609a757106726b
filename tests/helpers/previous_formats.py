"""Caches and results files as graftcache's previous format (1) left them: the one place tests write them
(tests/test_previous_formats.py reads them back through the one upgrade path, or sees them refused)."""

from __future__ import annotations

from pathlib import Path

import polars as pl

from graftcache.store.manifest import PREVIOUS_GAPS
from helpers.caches import rekeyed


def previous_format(folder: Path, root: Path, lacking: str | None = None) -> Path:
    """Where a copy of the cache in `folder` now lies as graftcache's previous format (1) stored it, under `root`
    in the folder of the key that manifest hashes to: fields outside the format at the top level, and, when
    `lacking` names one of store.manifest.PREVIOUS_GAPS ("frame_stride", ...), made before graftcache recorded
    it (a metadata-only dataset identity for "dataset_fingerprint.files")."""
    def older(stored: dict) -> dict:
        old = {**{k: v for k, v in stored.items() if k != "extra"}, **stored["extra"], "format_version": 1}
        if lacking == "dataset_fingerprint.files":
            old["dataset_fingerprint"] = {"codebase_version": "v3.0", "meta/info.json": "0" * 64}
        elif lacking is not None:
            assert lacking in dict(PREVIOUS_GAPS), lacking
            del old[lacking]
        return old
    return rekeyed(folder, root, older)


def previous_results(path: Path, rows: pl.DataFrame) -> Path:
    """`rows` (a results table of this format) written to `path` as format 1 wrote them: without the
    format_version column, which format 1 did not have."""
    rows.drop("format_version").write_parquet(path)
    return path
