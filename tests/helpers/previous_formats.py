"""Caches and results files as graftcache's previous formats (1 and 2; results also 3 and 4) left them: the one place
tests write them (tests/test_previous_formats.py reads them back through the one upgrade path, or sees them refused)."""

from __future__ import annotations

from pathlib import Path

import polars as pl

from graftcache.store.manifest import PREVIOUS_GAPS, RENAMED
from helpers.caches import rekeyed


def previous_format(folder: Path, root: Path, lacking: str | None = None, version: int = 1) -> Path:
    """Where a copy of the cache in `folder` now lies as graftcache's format `version` (1 or 2) stored it, under
    `root` in the folder of the key that manifest hashes to: the keys store.manifest.RENAMED has renamed since
    under their former names, and of format 1 the fields outside the format at the top level and, when `lacking`
    names one of store.manifest.PREVIOUS_GAPS ("frame_stride", ...), made before graftcache recorded it (a
    metadata-only dataset identity for "dataset_fingerprint.files")."""
    former = {new: old for old, new in RENAMED.items()}

    def older(stored: dict) -> dict:
        old = {former.get(k, k): v for k, v in stored.items()}
        if version == 1:
            old = {**{k: v for k, v in old.items() if k != "extra"}, **old["extra"]}
        old["format_version"] = version
        if lacking is not None:
            assert version == 1 and lacking in dict(PREVIOUS_GAPS), lacking
            head, _, sub = lacking.partition(".")
            if sub:
                old[head] = {"codebase_version": "v3.0", "meta/info.json": "0" * 64}
            else:
                del old[head]
        return old
    return rekeyed(folder, root, older)


#: The columns results format 4 added (issue 31; issue 32 the last two), which rows of formats 1 to 3 lack.
FORMAT_4_COLUMNS = ("eval_split", "eval_mse_arm", "eval_mse_gripper", "encoder_random_init", "backbone_random_init")
#: The columns results format 5 added (issue 41: the cell fields rows had not recorded), which rows of formats 1 to 4
#: lack.
FORMAT_5_COLUMNS = ("eval_fraction", "eval_frames", "num_denoise_steps", "lora_rank")
#: The column results format 6 added (the policy's identity), which rows of formats 1 to 5 lack.
FORMAT_6_COLUMNS = ("policy_id",)
#: The column results format 7 added (the kernels that computed the row), which rows of formats 1 to 6 lack.
FORMAT_7_COLUMNS = ("kernels",)


def previous_results(path: Path, rows: pl.DataFrame, version: int = 1) -> Path:
    """`rows` (a results table of this format) written to `path` as format `version` held them: format 1 had no
    format_version column; format 2 hashed cells whose pool_grid was "native" (the backbone's token grid,
    unresolved), so its run_ids are of cells of another shape; format 3 lacked FORMAT_4_COLUMNS, format 4
    FORMAT_5_COLUMNS, format 5 FORMAT_6_COLUMNS, format 6 FORMAT_7_COLUMNS."""
    rows = rows.drop(FORMAT_4_COLUMNS) if version <= 3 else rows
    rows = rows.drop(FORMAT_5_COLUMNS) if version <= 4 else rows
    rows = rows.drop(FORMAT_6_COLUMNS) if version <= 5 else rows
    rows = rows.drop(FORMAT_7_COLUMNS) if version <= 6 else rows
    old = rows.drop("format_version") if version == 1 else rows.with_columns(pl.lit(version).alias("format_version"))
    old.write_parquet(path)
    return path
