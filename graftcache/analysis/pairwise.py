"""Which encoder wins, offline and in closed loop? One verdict per pair of candidate encoders.

The question a user brings is not whether offline scores and closed-loop progress correlate over a cloud of
policies, but which of two encoders to pick and whether it wins on the robot too. Both sides answer it best
paired, because most of each side's noise is shared by the two encoders and cancels in their difference:

- offline: per fit seed both encoders have (a finite eval_mse in a plain row, control "none"), the difference
  eval_mse(A, seed) - eval_mse(B, seed): the two projectors of one seed are scored on the same eval frames;
- closed loop: per pair (fit seed, episode key PAIR_KEY) that A's and B's plain cells of that seed both ran with
  the measure recorded, A's value minus B's: the same scene, perturbation draw and step limit (episode keys are
  counted once per policy, graftcache.analysis.policies).

Each side's `*_difference` is the mean of its paired differences, with the paired Student-t interval at `level`
(mean +- t_{(1+level)/2, n-1} sd / sqrt(n)), the interval of scipy.stats.ttest_rel; a side is resolved where its
interval excludes 0, and then `offline` / `closed` names the better encoder, "a" or "b" (lower eval_mse is better;
the measure is oriented by HIGHER_IS_BETTER), else "not resolved". Where every paired difference is the same the
interval is that value (no spread: resolved unless it is 0, and the note says so). With fewer than 2 paired
differences a side has no interval; its call and the verdict are null and `note` says why.

`verdict`: "agree" or "disagree" where both sides are resolved (the same encoder better, or not), "offline only"
or "closed loop only" where one is, "neither" where none is. A t interval draws nothing at random, so the table
does not depend on `seed`, which `pairwise` takes as every closed-loop question does.
"""

from __future__ import annotations

import itertools

import numpy as np
import polars as pl
from scipy import stats

from graftcache.analysis.policies import KEY, POLICY, policies, policy_episodes
from graftcache.analysis.rollouts import HIGHER_IS_BETTER, MEASURES
from graftcache.analysis.table import GROUP, PLAIN
from graftcache.errors import GraftcacheError

A_BETTER, B_BETTER, NOT_RESOLVED = "a", "b", "not resolved"
AGREE, DISAGREE, OFFLINE_ONLY, CLOSED_ONLY, NEITHER = (
    "agree", "disagree", "offline only", "closed loop only", "neither")
PAIRWISE_SCHEMA = {
    "backbone": pl.String, "suite": pl.String, "measure": pl.String, "encoder_a": pl.String,
    "encoder_b": pl.String, "seeds": pl.Int64, "offline_difference": pl.Float64, "offline_low": pl.Float64,
    "offline_high": pl.Float64, "offline": pl.String, "pairs": pl.Int64, "closed_difference": pl.Float64,
    "closed_low": pl.Float64, "closed_high": pl.Float64, "closed": pl.String, "verdict": pl.String,
    "note": pl.String,
}
SUMMARY_SCHEMA = {"backbone": pl.String, "suite": pl.String, "measure": pl.String, "encoder_pairs": pl.Int64,
                  "resolved_by_both": pl.Int64, "agree": pl.Int64}
RESULTS_NEEDS = ("backbone", "suite", "encoder", "control", "seed", "run_id", "eval_mse")


def paired_t(diffs: np.ndarray, level: float) -> tuple[float | None, float | None, float | None]:
    """Mean of the paired differences and its Student-t interval at `level` (None without 2 of them)."""
    if not len(diffs):
        return None, None, None
    mean = float(diffs.mean())
    if len(diffs) < 2:
        return mean, None, None
    half = stats.t.ppf((1 + level) / 2, len(diffs) - 1) * diffs.std(ddof=1) / np.sqrt(len(diffs))
    return mean, mean - half, mean + half


def _call(low: float | None, high: float | None, lower_is_better: bool) -> str | None:
    """Which side the interval of A - B puts ahead, or NOT_RESOLVED where it holds 0."""
    if low is None:
        return None
    if high < 0 or low > 0:
        return A_BETTER if (high < 0) == lower_is_better else B_BETTER
    return NOT_RESOLVED


def _verdict(offline: str | None, closed: str | None) -> str | None:
    if offline is None or closed is None:
        return None
    resolved = (offline != NOT_RESOLVED, closed != NOT_RESOLVED)
    if all(resolved):
        return AGREE if offline == closed else DISAGREE
    return {(True, False): OFFLINE_ONLY, (False, True): CLOSED_ONLY, (False, False): NEITHER}[resolved]


def _side(name: str, count: str, n: int, diffs: np.ndarray) -> str | None:
    """Why a side has no interval (or has one of zero width), or None."""
    if n < 2:
        return f"{name}: {n} {count}, an interval needs 2"
    if np.ptp(diffs) == 0:
        return f"{name}: every paired difference is {diffs[0]:.4g}, a zero-width interval"
    return None


def _offline(plain: pl.DataFrame, a: str, b: str) -> np.ndarray:
    """eval_mse(A, seed) - eval_mse(B, seed) over the seeds both have finite, by seed."""
    finite = plain.filter(pl.col("eval_mse").is_finite())
    side = {e: finite.filter(pl.col("encoder") == e).select("seed", pl.col("eval_mse").alias(e)) for e in (a, b)}
    both = side[a].join(side[b], on="seed", how="inner").sort("seed")
    return (both[a] - both[b]).to_numpy()


def _closed(plain: pl.DataFrame, episodes: pl.DataFrame, a: str, b: str, measure: str) -> np.ndarray:
    """A's value minus B's over the (fit seed, episode key) pairs both plain cells ran with the measure."""
    value = pl.col(measure).cast(pl.Float64)
    recorded = episodes.filter(pl.all_horizontal(pl.col(KEY).is_not_null()), value.is_not_null())
    side = {e: recorded.join(plain.filter(pl.col("encoder") == e).select(POLICY, "seed"), left_on=POLICY,
                             right_on=POLICY, how="inner", suffix="_fit").select("seed_fit", *KEY, value.alias(e))
            for e in (a, b)}
    both = side[a].join(side[b], on=["seed_fit", *KEY], how="inner").sort("seed_fit", *KEY)
    return (both[a] - both[b]).to_numpy()


def _check(results: pl.DataFrame, rollouts: pl.DataFrame, measure: str, levels: tuple[float, ...]) -> None:
    if measure not in MEASURES:
        raise GraftcacheError(f"pairwise: measure {measure!r} is not one of {', '.join(MEASURES)}")
    for level in levels:
        if not 0 < level < 1:
            raise GraftcacheError(f"pairwise: level {level} is not between 0 and 1")
    for what, table, needs in (("results", results, RESULTS_NEEDS), ("rollouts", rollouts, ("run_id", measure, *KEY))):
        missing = [c for c in needs if c not in table.columns]
        if missing:
            raise GraftcacheError(f"pairwise: {what} table lacks column(s) {', '.join(missing)}")


def _plain_policies(results: pl.DataFrame) -> pl.DataFrame:
    """The candidates: one row per plain policy, refusing two policies for one (backbone, suite, encoder, seed)."""
    plain = policies(results.filter(pl.col("control") == PLAIN))
    dup = plain.group_by(*GROUP, "encoder", "seed").len().filter(pl.col("len") > 1)
    if len(dup):
        b, s, e, seed, _ = dup.row(0)
        raise GraftcacheError(f"pairwise: results rows of different policies share {b}/{s}/{e}/{PLAIN}/seed {seed}: "
                              "filter the table to one recipe")
    return plain


def pairwise(results: pl.DataFrame, rollouts: pl.DataFrame, *, measure: str = "min_target_distance_m",
             level: float = 0.95, closed_level: float | None = None, seed: int = 0) -> pl.DataFrame:
    """One PAIRWISE_SCHEMA row per (backbone, suite) of `results`' plain rows, in that order, and pair of their encoders
    (encoder_a < encoder_b by name): the offline and closed-loop paired differences A - B of `measure` over
    `rollouts` (read_rollouts), each with its paired t interval at `level` (the closed loop's at `closed_level` where
    given: a sequential rollout's looks, graftcache.analysis.looks), and the verdict (module docstring).
    `seed` is accepted for a uniform signature; nothing here is random."""
    closed_level = level if closed_level is None else closed_level
    _check(results, rollouts, measure, (level, closed_level))
    plain = _plain_policies(results)
    episodes = policy_episodes(results, rollouts)
    lower_is_better = not HIGHER_IS_BETTER[measure]
    records = []
    for (backbone, suite), group in plain.sort(GROUP).group_by(GROUP, maintain_order=True):
        for a, b in itertools.combinations(sorted(set(group["encoder"])), 2):
            offline, closed = _offline(group, a, b), _closed(group, episodes, a, b, measure)
            d_off, lo_off, hi_off = paired_t(offline, level)
            d_cl, lo_cl, hi_cl = paired_t(closed, closed_level)
            call_off, call_cl = _call(lo_off, hi_off, True), _call(lo_cl, hi_cl, lower_is_better)
            notes = [_side("offline", "seeds both encoders have", len(offline), offline),
                     _side("closed loop", "pairs (fit seed, episode key) both ran", len(closed), closed)]
            records.append({
                "backbone": backbone, "suite": suite, "measure": measure, "encoder_a": a, "encoder_b": b,
                "seeds": len(offline), "offline_difference": d_off, "offline_low": lo_off, "offline_high": hi_off,
                "offline": call_off, "pairs": len(closed), "closed_difference": d_cl, "closed_low": lo_cl,
                "closed_high": hi_cl, "closed": call_cl, "verdict": _verdict(call_off, call_cl),
                "note": "; ".join(n for n in notes if n) or None})
    return pl.DataFrame(records, schema=PAIRWISE_SCHEMA)


def pairwise_summary(table: pl.DataFrame) -> pl.DataFrame:
    """Per (backbone, suite, measure) of a pairwise table: its encoder pairs, those resolved by both sides, and
    how many of these agree ("k of n pairs resolved by both agree")."""
    both = pl.col("verdict").is_in([AGREE, DISAGREE])
    return table.group_by("backbone", "suite", "measure", maintain_order=True).agg(
        encoder_pairs=pl.len(), resolved_by_both=both.sum(), agree=(pl.col("verdict") == AGREE).sum(),
    ).select([pl.col(c).cast(t) for c, t in SUMMARY_SCHEMA.items()])
