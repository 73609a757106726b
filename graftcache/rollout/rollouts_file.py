"""The rollouts file: one row per simulated episode, its schema declared once and validated on every read and write
(rows are written by graftcache.rollout.record.append).

It is kept the way results files are (graftcache.results.writing.append_table: appends under the file's lease, a
temporary file renamed over it, readers through one descriptor), so several `graftcache rollout` processes may share
one file and a killed one leaves whole rows only. An episode is identified by `episode_id`, the hash of what decides it
(EPISODE_KEY): a rerun of the same command finds its episodes there and adds none; a rerun with another seed,
step limit, task or perturbation adds its own.

Format 2 added the graded progress of each episode (graftcache.rollout.graded: the definitions, after SIMPLER, arXiv
2405.05941) and the target's perturbation (graftcache.rollout.perturb); a format-1 file is read with those columns
null (FORMAT_2_COLUMNS), its episode_ids unchanged (an episode without a perturbation hashes as format 1 hashed
it).

Format 3 added `kernels`: where the episode's policy computed (graftcache.runtime.kernels of `rollout --device`), since
an action computed on other kernels differs in its last bits and the episode after it may differ; rows of formats 1 and
2 (all computed on a CPU) read with it null.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import polars as pl

from graftcache.errors import GraftcacheError, RolloutError
from graftcache.hashing import sha256_json
from graftcache.results.reading import failure_reason, load_table
from graftcache.results.schema import cast_exactly

#: The format of rollouts rows (independent of the results' format); a newer one is refused by `read`.
FORMAT_VERSION = 3
#: The fields that decide an episode, hashed into its `episode_id`, with `perturbation_m` when it is not 0.
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
    # format 2 (null in format-1 rows; graftcache.rollout.graded.Graded defines each, after SIMPLER)
    "target": pl.String,              # the task's first object of interest (its BDDL's obj_of_interest[0])
    "perturbation_m": pl.Float64,     # the largest planar target offset asked per axis (--perturb-cm / 100); 0.0:
                                      # lerobot-eval's official init states
    "target_offset_x_m": pl.Float64,  # the planar offset applied to the target (0, 0 when none, or when no draw
    "target_offset_y_m": pl.Float64,  # settled: graftcache.rollout.perturb)
    "min_target_distance_m": pl.Float64,    # min over every state (after the reset, after each step) of |eef - target|
    "final_target_distance_m": pl.Float64,  # |eef - target| at the episode's last state
    "target_lift_m": pl.Float64,      # the target's highest height above its settled height after the reset (>= 0)
    "grasped": pl.Boolean,            # both gripper fingers touching the target for >= 5 consecutive states
    "goal_fraction": pl.Float64,      # share of the task's BDDL goal predicates true at the last state
    "kernels": pl.String,             # format 3: where its policy computed (graftcache.runtime.kernels), e.g.
                                      # "cpu:avx512+amx" or "cuda:sm_90"; null: not recorded
    "lerobot_version": pl.String,
    "graftcache_version": pl.String,
    "command": pl.String,             # the command line that ran it
}


#: The columns format 2 added (the graded measures, the target and the perturbation): a format-1 row reads with them
#: null
FORMAT_2_COLUMNS = ("target", "perturbation_m", "target_offset_x_m", "target_offset_y_m", "min_target_distance_m",
                    "final_target_distance_m", "target_lift_m", "grasped", "goal_fraction")
#: The columns each format added: a file whose rows all predate a format reads with that format's columns null
ADDED_COLUMNS: dict[int, tuple[str, ...]] = {2: FORMAT_2_COLUMNS, 3: ("kernels",)}


def episode_id(fields: Mapping[str, Any]) -> str:
    """The id of the episode decided by `fields` (EPISODE_KEY's values, and `perturbation_m`): a perturbed episode is
    another episode, while one on the official init states keeps the id format 1 gave it."""
    key = {k: fields[k] for k in EPISODE_KEY}
    if fields.get("perturbation_m"):
        key["perturbation_m"] = fields["perturbation_m"]
    return sha256_json(key)[:16]


def empty() -> pl.DataFrame:
    return pl.DataFrame(schema=SCHEMA)


def validate(rows: pl.DataFrame) -> pl.DataFrame:
    """`rows` cast to SCHEMA, refusing missing or extra columns and a value its column would change."""
    missing = [c for c in SCHEMA if c not in rows.columns]
    extra = [c for c in rows.columns if c not in SCHEMA]
    if missing or extra:
        raise GraftcacheError(f"rollouts rows do not match the schema: missing {missing}, unexpected {extra}")
    return pl.DataFrame([cast_exactly(rows[c], t) for c, t in SCHEMA.items()])


def read(path: str | Path) -> pl.DataFrame:
    """The rollouts file at `path` (an absent file: no rows); anything else than rollouts rows of this format or
    older is a RolloutError naming the file."""
    path = Path(path)
    if not path.exists():
        return empty()
    try:
        table = load_table(path)
    except (pl.exceptions.PolarsError, OSError) as e:
        raise RolloutError(f"{path}: not a Parquet rollouts table ({failure_reason(e, path)}); pass another "
                           "--rollouts") from None
    if "episode_id" not in table.columns:
        what = "a results table" if "eval_mse" in table.columns else "no rollouts table"
        raise RolloutError(f"{path}: {what}, not rollouts rows (no episode_id column); pass another --rollouts")
    if "format_version" in table.columns and (table["format_version"] > FORMAT_VERSION).any():
        raise RolloutError(f"{path}: rollouts rows of format {table['format_version'].max()}, newer than this "
                           f"graftcache's ({FORMAT_VERSION}): pass another --rollouts")
    for version, added in ADDED_COLUMNS.items():
        old = [c for c in added if c not in table.columns]
        if old and "format_version" in table.columns and (table["format_version"] < version).all():
            table = table.with_columns(pl.lit(None, SCHEMA[c]).alias(c) for c in old)  # not recorded then
    try:
        return validate(table)
    except GraftcacheError as e:
        raise RolloutError(f"{path}: {e}; pass another --rollouts") from None

