"""Seed stability: would a rerun with other seeds reach the verdicts the report gives?

The report says "transfers" or "does not transfer" from every seed's rows at once. A rerun with other seeds
reaches the same verdict only where the verdict, and the target's top tier it rests on, do not hang on which
seeds ran. This repeats each (suite, pair, direction) comparison on a part of the seeds and says whether the part
gives the same verdict and the same target top tier as all seeds: each seed alone, or, with HALVES_FROM seeds or
more, the two disjoint halves of the seeds (a half has seeds enough for a bootstrap of its own, one seed has
only its held-out episodes). Each seed alone is what seed_verdicts already judged (the same rows, the same
bootstrap draws), so it is read from there, not judged again.
"""

from __future__ import annotations

import polars as pl

from graftcache.analysis.ladder import Ladder
from graftcache.analysis.stats import BootSettings
from graftcache.analysis.table import PLAIN, control_rows
from graftcache.analysis.transfer import INSUFFICIENT, transfer_verdicts

#: From this many seeds on, the parts are the two halves of the seeds, not each seed alone.
HALVES_FROM = 4

STABILITY_SCHEMA = {
    "suite": pl.String,
    "source": pl.String,
    "target": pl.String,
    "part": pl.String,                       # which seeds judged it alone: "seed 1", "seeds 0, 1"
    "verdict": pl.String,                    # from all seeds (transfer_verdicts)
    "part_verdict": pl.String,               # from the part's seeds alone
    "target_band": pl.List(pl.String),       # the target's top tier from all seeds
    "part_band": pl.List(pl.String),         # ... from the part's seeds alone
    "same_verdict": pl.Boolean,              # null: the part could not be judged (INSUFFICIENT)
    "same_tier": pl.Boolean,                 # null: as same_verdict
}
_KEY = ["suite", "source", "target"]


def seed_parts(seeds: list[int]) -> list[tuple[int, ...]]:
    """Each seed alone, or with HALVES_FROM seeds or more the lower and the upper half of the sorted seeds (an odd
    count leaves the extra seed in the upper half); one seed or none: no parts, stability cannot be measured."""
    seeds = sorted(seeds)
    if len(seeds) < 2:
        return []
    if len(seeds) < HALVES_FROM:
        return [(s,) for s in seeds]
    half = len(seeds) // 2
    return [tuple(seeds[:half]), tuple(seeds[half:])]


def part_label(part: tuple[int, ...]) -> str:
    return f"seed {part[0]}" if len(part) == 1 else "seeds " + ", ".join(map(str, part))


def seed_stability(results: pl.DataFrame, verdicts: pl.DataFrame, seed_verdicts: pl.DataFrame, *, ladder: Ladder,
                   boot: BootSettings = BootSettings()) -> pl.DataFrame:
    """Per judged comparison (an all-seeds verdict other than INSUFFICIENT) and part of the seeds (seed_parts of
    the seeds with valid plain rows): the part's verdict and target top tier beside all seeds'. Empty with fewer
    than two seeds."""
    parts = seed_parts(control_rows(results, PLAIN).drop_nulls("eval_mse")["seed"].unique().to_list())
    if not parts:
        return pl.DataFrame(schema=STABILITY_SCHEMA)
    if len(parts[0]) == 1:
        alone = seed_verdicts.with_columns(part=pl.format("seed {}", pl.col("seed")))
    else:
        alone = pl.concat([transfer_verdicts(results.filter(pl.col("seed").is_in(p)), ladder=ladder, boot=boot)
                           .with_columns(part=pl.lit(part_label(p))) for p in parts])
    judged = verdicts.filter(pl.col("verdict") != INSUFFICIENT).select(*_KEY, "verdict", "target_band")
    joined = judged.join(alone.select(*_KEY, "part", part_verdict="verdict", part_band="target_band"), on=_KEY,
                         how="inner", maintain_order="left")
    can = pl.col("part_verdict") != INSUFFICIENT
    return joined.with_columns(
        same_verdict=pl.when(can).then(pl.col("verdict") == pl.col("part_verdict")),
        same_tier=pl.when(can).then(pl.col("target_band").list.sort() == pl.col("part_band").list.sort()),
    ).select(list(STABILITY_SCHEMA)).cast(STABILITY_SCHEMA)
