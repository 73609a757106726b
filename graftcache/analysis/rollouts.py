"""What the report reads of a rollouts file: each episode's `run_id` (the results row whose policy ran it) and
`success`, and where the file has them, the graded measures of closed-loop progress and the episode's key.

Only `run_id` and `success` are required, so episodes a user ran with other tools join as well as those
`graftcache rollout` writes. The graded columns (GRADED_MEASURES; format-2 rollouts rows,
graftcache.rollout.rollouts_file) and the key that pairs one episode across cells (PAIR_KEY) are read when present
and null when absent: a format-1 file, or a user's table without them, still reads, and the report says that its
graded measures are unavailable rather than leaving those rollouts out. The column names and types are the rollouts
contract's, written out here rather than imported: analysis reads files, it does not depend on the code that writes
them.

An episode whose run_id is not in the results table is refused (one line naming the file and such a run_id), never
dropped: rollouts of another results file would otherwise leave the report silently about fewer cells. So is a
column of the wrong type, a non-finite graded value (a distance of NaN is a bug upstream, not a measurement) and
one the measure cannot take (RANGES: a negative distance, a goal fraction of 7).

An episode that appears more than once is refused too (one line naming the file, the episode and its copies), not
de-duplicated: `graftcache rollout` replaces an episode it reruns, so a second copy comes from rows appended by other
means (two files concatenated, a copy appended by hand), whose copies may disagree on success; keeping one would
guess which, and counting both weighs that episode twice in every figure. An episode is its `episode_id` where the
file has one, else its run_id and PAIR_KEY where every key column but perturbation_m is set (a table without a key
cannot tell a repeated episode from another one).
"""

from __future__ import annotations

import math
from pathlib import Path

import polars as pl

from graftcache.errors import GraftcacheError, first_line

ROLLOUT_COLUMNS = ("run_id", "success")
#: The graded measures of progress, per episode, from the simulator's state (null where a row lacks them).
GRADED_MEASURES: dict[str, pl.DataType] = {
    "min_target_distance_m": pl.Float64,    # closest approach of the end effector to the task's target
    "final_target_distance_m": pl.Float64,  # that distance at the episode's last state
    "target_lift_m": pl.Float64,            # the target's highest height above its settled height
    "grasped": pl.Boolean,                  # target held between both fingers for >= 5 consecutive steps
    "goal_fraction": pl.Float64,            # share of the task's BDDL goal predicates true at the end
}
#: The values each graded measure can take (graftcache.rollout.graded defines them: a distance and the clipped lift
#: are >= 0, a share of goal predicates is in [0, 1]); a value outside is refused, not scored.
RANGES: dict[str, tuple[float, float]] = {
    "min_target_distance_m": (0.0, math.inf), "final_target_distance_m": (0.0, math.inf),
    "target_lift_m": (0.0, math.inf), "goal_fraction": (0.0, 1.0),
}
#: Every closed-loop measure and whether higher is better; the report orients each agreement figure by it.
HIGHER_IS_BETTER: dict[str, bool] = {
    "success": True, "min_target_distance_m": False, "final_target_distance_m": False, "target_lift_m": True,
    "grasped": True, "goal_fraction": True,
}
MEASURES = tuple(HIGHER_IS_BETTER)
#: Where an episode's policy computed (rollouts format 3; graftcache.runtime.kernels): read where the file has it, so
#: that the report can say when the episodes it compares were computed on other kernels (null: not recorded).
PROVENANCE: dict[str, pl.DataType] = {"kernels": pl.String}
#: What decides an episode apart from the policy: the same key in two cells is the same scene, seed and limit.
PAIR_KEY: dict[str, pl.DataType] = {
    "suite": pl.String, "task_index": pl.Int64, "episode": pl.Int64, "seed": pl.Int64, "max_steps": pl.Int64,
    "perturbation_m": pl.Float64,
}


def _boolean(column: pl.Series, path: Path) -> pl.Series:
    """A true/false column as booleans: booleans as they are, integers only when every one is 0 or 1."""
    values = column.drop_nulls()
    if column.dtype in (pl.Boolean, pl.Null):
        return column.cast(pl.Boolean)
    if column.dtype.is_integer() and values.is_in([0, 1]).all():
        return column.cast(pl.Boolean)
    odd = values.filter(~values.is_in([0, 1])) if column.dtype.is_numeric() else values
    raise GraftcacheError(f"{path}: column {column.name} holds {column.dtype} values such as {odd[0]!r}, not "
                          "true/false")


def _typed(column: pl.Series, dtype: pl.DataType, path: Path) -> pl.Series:
    """`column` as `dtype`, refusing a value that would change (text for a number, 1.5 for an integer)."""
    if dtype == pl.Boolean:
        return _boolean(column, path)
    if column.dtype == pl.Null or column.dtype == dtype:
        return column.cast(dtype)
    fits = (dtype == pl.String and column.dtype in (pl.String, pl.Categorical, pl.Enum)) or (
        dtype == pl.Float64 and column.dtype.is_numeric()) or (dtype == pl.Int64 and column.dtype.is_integer())
    if not fits:
        raise GraftcacheError(f"{path}: column {column.name} holds {column.dtype} values, not {dtype}")
    return column.cast(dtype)


def _read(path: Path) -> pl.DataFrame:
    if not path.is_file():
        raise GraftcacheError(f"{path}: no rollouts file")
    try:
        return pl.read_parquet(path)
    except (pl.exceptions.PolarsError, OSError) as e:
        raise GraftcacheError(f"{path}: not a Parquet rollouts table ({first_line(e)})") from None


def _episode_keys(table: pl.DataFrame, rollouts: pl.DataFrame) -> pl.DataFrame:
    """What identifies each row's episode: `episode_id` where the file has it, else run_id and PAIR_KEY (a null
    perturbation_m read as 0.0, as the pairing reads it), leaving out rows whose key is incomplete."""
    if "episode_id" in table.columns:
        return table.select(pl.col("episode_id").cast(pl.String)).drop_nulls()
    key = ["run_id", *PAIR_KEY]
    return rollouts.select(key).with_columns(pl.col("perturbation_m").fill_null(0.0)).drop_nulls()


def _refuse_repeats(table: pl.DataFrame, rollouts: pl.DataFrame, path: Path) -> None:
    """Refuse an episode that appears more than once (the module docstring says why it is not de-duplicated)."""
    keys = _episode_keys(table, rollouts)
    counts = keys.group_by(keys.columns, maintain_order=True).len("copies").filter(pl.col("copies") > 1)
    if not len(counts):
        return
    first = counts.row(0, named=True)
    copies = first.pop("copies")
    episode = ", ".join(f"{k}={v}" for k, v in first.items())
    more = f" (and {len(counts) - 1} more repeated episode(s))" if len(counts) > 1 else ""
    raise GraftcacheError(f"{path}: episode {episode} appears {copies} times{more}: each episode must be one row; "
                          "keep one copy of each")


def _refuse_out_of_range(rollouts: pl.DataFrame, path: Path) -> None:
    """Refuse the first graded column holding a value outside its RANGES, naming an example."""
    for column, (low, high) in RANGES.items():
        outside = rollouts[column].filter((rollouts[column] < low) | (rollouts[column] > high))
        if len(outside):
            allowed = f">= {low:g}" if high == math.inf else f"in [{low:g}, {high:g}]"
            raise GraftcacheError(f"{path}: column {column} holds {outside[0]!r}, not a possible value (the measure "
                                  f"is {allowed}; graftcache.rollout.graded)")


def read_rollouts(path: str | Path, results: pl.DataFrame, *, where: pl.Expr | None = None) -> pl.DataFrame:
    """The rollouts Parquet file at `path` as one row per episode: run_id, success, GRADED_MEASURES, PAIR_KEY and
    PROVENANCE (each null where the file lacks it), checked against `results`' run_ids; anything unusable is a
    GraftcacheError naming the file. `where`: only the file's rows it holds true for, on the file's own columns (a
    sequential rollout's look reads the episodes it decides on, graftcache.rollout.sequential)."""
    path = Path(path)
    table = _read(path)
    if where is not None:
        try:
            table = table.filter(where)
        except pl.exceptions.PolarsError as e:
            raise GraftcacheError(f"{path}: cannot select its rows ({first_line(e)})") from None
    missing = [c for c in ROLLOUT_COLUMNS if c not in table.columns]
    if missing:
        raise GraftcacheError(f"{path}: rollouts table lacks column(s) {', '.join(missing)} (the report needs "
                              f"{', '.join(ROLLOUT_COLUMNS)} per episode)")
    if not len(table):
        raise GraftcacheError(f"{path}: no rollouts (no rows)")
    nulls = [c for c in ROLLOUT_COLUMNS if table[c].null_count()]
    if nulls:
        raise GraftcacheError(f"{path}: null values in column(s) {', '.join(nulls)}")
    optional = {**GRADED_MEASURES, **PAIR_KEY, **PROVENANCE}
    columns = [table["run_id"].cast(pl.String), _boolean(table["success"], path)]
    columns += [_typed(table[c], t, path) if c in table.columns else pl.Series(c, [None] * len(table), dtype=t)
                for c, t in optional.items()]
    rollouts = pl.DataFrame(columns)
    _refuse_repeats(table, rollouts, path)
    odd = [c for c, t in GRADED_MEASURES.items() if t == pl.Float64 and (~rollouts[c].is_finite()).any()]
    if odd:
        raise GraftcacheError(f"{path}: non-finite values in column(s) {', '.join(odd)} (null: not measured)")
    _refuse_out_of_range(rollouts, path)
    unknown = rollouts.filter(~pl.col("run_id").is_in(results["run_id"].implode()))["run_id"].unique(
        maintain_order=True)
    if len(unknown):
        raise GraftcacheError(f"{path}: {len(unknown)} run_id(s) not in the results table, e.g. {unknown[0]}: pass "
                              "the results file whose rows were rolled out")
    return rollouts
