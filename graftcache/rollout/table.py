"""The rollouts file: one row per simulated episode, its schema declared once and validated on every write.

It is kept the way results files are (graftcache.results.append_table: appends under the file's lease, a temporary
file renamed over it, readers through one descriptor), so several `graftcache rollout` processes may share one file
and a killed one leaves whole rows only. An episode is identified by `episode_id`, the hash of what decides it
(EPISODE_KEY): a rerun of the same command finds its episodes there and adds none; a rerun with another seed,
step limit or task adds its own.

The report reads only `run_id` and `success` (graftcache.analysis.rollouts); every other column is provenance.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import polars as pl

from graftcache import results
from graftcache.errors import GraftcacheError, RolloutError
from graftcache.hashing import sha256_json

#: The format of rollouts rows (independent of the results' format); a newer one is refused by `read`.
FORMAT_VERSION = 1
#: The fields that decide an episode, hashed into its `episode_id`.
EPISODE_KEY = ("run_id", "suite", "task_index", "episode", "seed", "max_steps")

SCHEMA: dict[str, pl.DataType] = {
    "episode_id": pl.String,          # sha256 of EPISODE_KEY's values, 16 hex: what a rerun skips by
    "format_version": pl.Int64,       # FORMAT_VERSION of the row
    "run_id": pl.String,              # the results row whose cell was exported and ran the episode
    "suite": pl.String,               # LIBERO suite, e.g. "libero_object"
    "task_index": pl.Int64,           # task of the suite (lerobot's --env.task_ids)
    "episode": pl.Int64,              # episode of the task, 0..N-1 (lerobot-eval's episode index)
    "seed": pl.Int64,                 # the environment's seed: --seed + episode, as lerobot-eval seeds episode k
    "init_state": pl.Int64,           # index of the suite's official init state the episode started from
    "max_steps": pl.Int64,            # the step limit (lerobot's episode length of the suite, or --max-steps)
    "success": pl.Boolean,            # any step's check_success(), as lerobot-eval counts it
    "steps": pl.Int64,                # steps run: up to the first success, else max_steps
    "seconds": pl.Float64,            # wall time of the episode (reset, settling, every step), seconds
    "video": pl.String,               # the episode's mp4, relative to the rollouts file; null: none recorded
    "lerobot_version": pl.String,
    "graftcache_version": pl.String,
    "command": pl.String,             # the command line that ran it
}


def episode_id(fields: Mapping[str, Any]) -> str:
    """The id of the episode decided by `fields` (EPISODE_KEY's values)."""
    return sha256_json({k: fields[k] for k in EPISODE_KEY})[:16]


def empty() -> pl.DataFrame:
    return pl.DataFrame(schema=SCHEMA)


def validate(rows: pl.DataFrame) -> pl.DataFrame:
    """`rows` cast to SCHEMA, refusing missing or extra columns and a value its column would change."""
    missing = [c for c in SCHEMA if c not in rows.columns]
    extra = [c for c in rows.columns if c not in SCHEMA]
    if missing or extra:
        raise GraftcacheError(f"rollouts rows do not match the schema: missing {missing}, unexpected {extra}")
    return pl.DataFrame([results.cast_exactly(rows[c], t) for c, t in SCHEMA.items()])


def read(path: str | Path) -> pl.DataFrame:
    """The rollouts file at `path` (an absent file: no rows); anything else than rollouts rows of this format or
    older is a RolloutError naming the file."""
    path = Path(path)
    if not path.exists():
        return empty()
    try:
        table = results.load_table(path)
    except (pl.exceptions.PolarsError, OSError) as e:
        raise RolloutError(f"{path}: not a Parquet rollouts table ({results.failure_reason(e, path)}); pass another "
                           "--rollouts") from None
    if "episode_id" not in table.columns:
        what = "a results table" if "eval_mse" in table.columns else "no rollouts table"
        raise RolloutError(f"{path}: {what}, not rollouts rows (no episode_id column); pass another --rollouts")
    if "format_version" in table.columns and (table["format_version"] > FORMAT_VERSION).any():
        raise RolloutError(f"{path}: rollouts rows of format {table['format_version'].max()}, newer than this "
                           f"graftcache's ({FORMAT_VERSION}): pass another --rollouts")
    try:
        return validate(table)
    except GraftcacheError as e:
        raise RolloutError(f"{path}: {e}; pass another --rollouts") from None


def append(path: str | Path, rows: Iterable[Mapping[str, Any]]) -> pl.DataFrame:
    """Append episodes' rows (dicts of SCHEMA's columns) under the file's lease; an episode already there is
    replaced, never doubled."""
    new = validate(pl.DataFrame([dict(r) for r in rows], schema=SCHEMA))
    return results.append_table(path, new, read, key="episode_id", what="rollouts file")
