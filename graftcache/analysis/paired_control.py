"""The paired closed-loop control: does the backbone's own vision tower beat zero-image on the same episodes?

Offline, the native tower beating zero-image says the backbone reads its images; in the simulator the question is
whether that reading makes the policy act better, and a scene-by-scene comparison answers it with far fewer
episodes than two independent success rates would need, because both policies face the same scene, seed and step
limit and the scene's own difficulty cancels.

The pairing, per (backbone, suite) and closed-loop measure (graftcache.analysis.rollouts.MEASURES):
- the native side is every cell of control `native`, the zero-image side every cell of control `zero-image`; a
  cell is a policy (graftcache.analysis.policies), so a zero-image policy rolled out under several encoders, or
  a native tower under several seeds, is one cell, and its episodes count once;
- an episode key is PAIR_KEY (suite, task_index, episode, seed, max_steps, perturbation_m): the same key is the
  same scene. A null perturbation_m is read as 0.0 (format-1 rows and tables without the column were run from the
  official init states, policy_episodes reads it so); an episode with any other key column null cannot be paired
  and is left out;
- per key that both sides ran (with the measure recorded): d_k = the mean of the measure over the native episodes
  with that key minus its mean over the zero-image episodes with that key. Averaging each side within a key first
  makes the key one paired observation, whatever the number of cells on each side;
- `difference` is the mean of d_k over the paired keys (in the measure's units: a rate, metres, a fraction), with
  a 95% percentile interval from N_BOOT resamples of the keys (graftcache.analysis.closed_loop_boot);
- `better` is "native" where the whole interval lies on the native-is-better side (above 0 for a measure where
  higher is better, below 0 for a distance), "zero-image" where it lies on the other, else "not separated";
- `native_seeds_better` counts the native cells (`native_seeds`: distinct native policies) whose own mean of (its
  value - the zero-image mean of the key), over the keys it shares with zero-image, is on the better side: "on
  every seed" when it equals `native_seeds`.
Undefined (null, `note` says why) without a cell on either side or without a paired key; the interval and
`better` also with a single paired key (nothing to resample).
"""

from __future__ import annotations

import polars as pl

from graftcache.analysis.closed_loop_boot import interval, resampled_means
from graftcache.analysis.findings import NOT_SEPARATED
from graftcache.analysis.policies import POLICY
from graftcache.analysis.rollouts import HIGHER_IS_BETTER, MEASURES, PAIR_KEY
from graftcache.analysis.stats import generator
from graftcache.analysis.table import GROUP, NATIVE_CONTROL, ZERO_IMAGE

KEY = list(PAIR_KEY)
NATIVE_BETTER, ZERO_IMAGE_BETTER = "native", "zero-image"
CONTROL_SCHEMA = {
    "backbone": pl.String, "suite": pl.String, "measure": pl.String, "native_cells": pl.Int64,
    "zero_image_cells": pl.Int64, "pairs": pl.Int64, "native": pl.Float64, "zero_image": pl.Float64,
    "difference": pl.Float64, "ci_low": pl.Float64, "ci_high": pl.Float64, "better": pl.String,
    "native_seeds_better": pl.Int64, "native_seeds": pl.Int64, "note": pl.String,
}


def _pairable(cells: pl.DataFrame, episodes: pl.DataFrame) -> pl.DataFrame:
    """The episodes of native and zero-image cells whose key is whole, with their cell's group and control."""
    sides = cells.filter(pl.col("control").is_in([NATIVE_CONTROL, ZERO_IMAGE])).select(
        POLICY, *(pl.col(c).alias(f"cell_{c}") for c in GROUP), "control")
    return episodes.join(sides, on=POLICY, how="inner").drop_nulls(KEY)


def _compare(episodes: pl.DataFrame, measure: str, seed: int, what: tuple[str, ...]) -> dict:
    """The paired figures of one measure over one group's native and zero-image episodes (see the module
    docstring); `what` names the resampled keys' generator."""
    value = pl.col(measure).cast(pl.Float64)
    recorded = episodes.filter(value.is_not_null()).with_columns(value=value)
    zero = recorded.filter(pl.col("control") == ZERO_IMAGE).group_by(KEY).agg(zero=pl.col("value").mean())
    native = recorded.filter(pl.col("control") == NATIVE_CONTROL)
    per_key = native.group_by(KEY).agg(native=pl.col("value").mean()).join(zero, on=KEY, how="inner").sort(KEY)
    if not len(per_key):
        return {}
    sign = 1.0 if HIGHER_IS_BETTER[measure] else -1.0
    diffs = (per_key["native"] - per_key["zero"]).to_numpy()
    seeds = native.join(zero, on=KEY, how="inner").group_by(POLICY).agg(
        (pl.col("value") - pl.col("zero")).mean().alias("d"))
    out = {"pairs": len(per_key), "native": per_key["native"].mean(), "zero_image": per_key["zero"].mean(),
           "difference": float(diffs.mean()), "native_seeds": len(seeds),
           "native_seeds_better": int((sign * seeds["d"] > 0).sum())}
    if len(per_key) < 2:
        return out | {"note": "1 paired episode: no interval"}
    lo, hi = interval(resampled_means(diffs, generator(seed, "paired-control", *what)))
    better = (NATIVE_BETTER if min(sign * lo, sign * hi) > 0 else ZERO_IMAGE_BETTER if max(sign * lo, sign * hi) < 0
              else NOT_SEPARATED)
    return out | {"ci_low": lo, "ci_high": hi, "better": better}


def paired_control(cells: pl.DataFrame, episodes: pl.DataFrame, *, seed: int = 0) -> pl.DataFrame:
    """One CONTROL_SCHEMA row per (backbone, suite) of `cells` (graftcache.analysis.closed_loop.rollout_cells) and
    MEASURES measure: the native tower against zero-image on the same `episodes`
    (graftcache.analysis.policies.policy_episodes)."""
    pairable = _pairable(cells, episodes)
    records = []
    for (backbone, suite), group in cells.group_by(GROUP, maintain_order=True):
        counts = {c: int((group["control"] == c).sum()) for c in (NATIVE_CONTROL, ZERO_IMAGE)}
        episodes = pairable.filter(pl.col("cell_backbone") == backbone, pl.col("cell_suite") == suite)
        for measure in MEASURES:
            row = {"backbone": backbone, "suite": suite, "measure": measure, "native_cells": counts[NATIVE_CONTROL],
                   "zero_image_cells": counts[ZERO_IMAGE], "pairs": 0}
            missing = [c for c, n in counts.items() if not n]
            if missing:
                records.append(row | {"note": f"no {' and no '.join(missing)} cell with rollouts"})
                continue
            found = _compare(episodes, measure, seed, (backbone, suite, measure))
            if not found:
                unrecorded = episodes[measure].null_count() == len(episodes) and len(episodes)
                found = {"note": (f"graded measures unavailable: no native or zero-image episode records {measure}"
                                  if unrecorded else "no episode key (" + ", ".join(KEY) + ") was run by both "
                                  "a native and a zero-image cell")}
            records.append(row | found)
    return pl.DataFrame(records, schema=CONTROL_SCHEMA)
