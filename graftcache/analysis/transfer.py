"""Does the encoder ranking transfer between backbones? Verdicts in both directions, per suite and per
seed-level cell, their counts, seed-level top-1 agreement and Kendall's tau-b.

A *comparison* is (suite, direction); the directions are small -> large (is the small backbone's winner in
the large one's top tier?) and large -> small. A *seed-level cell* repeats the test on one seed's rows
alone, so 2 suites x 3 seeds give 12 cells against 4 comparisons, the paper's "k of n" counts.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import polars as pl

from graftcache.analysis.stats import BOOT_SEED, CONFIDENCE, N_BOOT, tau_b
from graftcache.analysis.summaries import near_tie_band, seed_summary
from graftcache.analysis.table import (
    LARGE,
    PLAIN,
    SMALL,
    backbone_label,
    control_rows,
    plain_backbones,
    plain_suites,
)

TRANSFERS = "transfers"
NEAR_TIE = "near-tie band"
DOES_NOT_TRANSFER = "does not transfer"
INSUFFICIENT = "insufficient data"
VERDICTS = (TRANSFERS, NEAR_TIE, DOES_NOT_TRANSFER, INSUFFICIENT)
# verdict_counts' column per verdict; n_judged counts every verdict but INSUFFICIENT
COUNT_COLUMNS = {
    TRANSFERS: "n_transfers",
    NEAR_TIE: "n_near_tie",
    DOES_NOT_TRANSFER: "n_does_not_transfer",
    INSUFFICIENT: "n_insufficient",
}

_DIRECTED = {
    "source": pl.String,
    "target": pl.String,
    "source_winner": pl.String,
    "target_winner": pl.String,
    "target_band": pl.List(pl.String),
    "n_common": pl.Int64,
    "verdict": pl.String,
    "basis": pl.String,
    "note": pl.String,
}
VERDICT_SCHEMA = {"suite": pl.String, **_DIRECTED}
SEED_VERDICT_SCHEMA = {"suite": pl.String, "seed": pl.Int64, **_DIRECTED}


def two_backbone_gap(results: pl.DataFrame, small: str = SMALL, large: str = LARGE) -> str | None:
    """Why no transfer question can be asked of this table (a backbone without valid plain rows), or None."""
    have = plain_backbones(results)
    lacking = [backbone_label(b) for b in (small, large) if b not in have]
    if not lacking:
        return None
    present = ", ".join(backbone_label(b) for b in sorted(have)) or "none"
    return f"needs two backbones ({backbone_label(small)} and {backbone_label(large)}); present: {present}"


def common_encoders(rows: pl.DataFrame, small: str, large: str) -> tuple[list[str], str | None]:
    """Encoders with valid plain rows on both backbones (rows of one suite), and a note naming the ones
    left out: a winner can only transfer within a shared set."""
    valid = control_rows(rows, PLAIN).drop_nulls("eval_mse")
    have = {b: set(valid.filter(pl.col("backbone") == b)["encoder"].to_list()) for b in (small, large)}
    common = sorted(have[small] & have[large])
    only = [
        f"{e} (only {backbone_label(b)})"
        for b, o in ((small, large), (large, small))
        for e in sorted(have[b] - have[o])
    ]
    return common, ("left out, not on both backbones: " + ", ".join(only)) if only else None


def _judge(common: list[str], source: str, target: str, band: pl.DataFrame) -> dict[str, Any]:
    """One direction's verdict from the top tiers of both backbones over the shared encoders.

    A target tier holding every shared encoder separates nothing: the source winner lands in it whatever
    the ranking, so that is a (seed-sensitive) near-tie band, not a transfer.
    """
    on_source = band.filter(pl.col("backbone") == source)
    on_target = band.filter(pl.col("backbone") == target).sort("mean", "encoder")
    winners = on_source.filter(pl.col("rank") == 1)["encoder"].sort().to_list()
    tier = on_target.filter(pl.col("in_band"))["encoder"].to_list()
    if set(tier) >= set(common):
        verdict = NEAR_TIE
    else:
        verdict = TRANSFERS if set(winners) <= set(tier) else DOES_NOT_TRANSFER
    return {
        "source_winner": ", ".join(winners),
        "target_winner": ", ".join(on_target.filter(pl.col("rank") == 1)["encoder"].sort().to_list()),
        "target_band": tier,
        "verdict": verdict,
        "basis": ", ".join(sorted(set(on_target["basis"].to_list()))),
    }


def _both_directions(
    rows: pl.DataFrame, where: dict[str, Any], gap: str | None, small: str, large: str, **boot: Any
) -> list[dict[str, Any]]:
    """The small -> large and large -> small records for one suite's rows (or one seed's): "insufficient
    data" with the reason in `note` when `gap` says why, or fewer than two encoders are shared."""
    common, note = ([], gap) if gap else common_encoders(rows, small, large)
    if not gap and len(common) < 2:
        note = "; ".join(x for x in (f"{len(common)} encoder(s) on both backbones", note) if x)
    records = [
        {**where, "source": s, "target": t, "n_common": len(common), "verdict": INSUFFICIENT, "note": note}
        for s, t in ((small, large), (large, small))
    ]
    if len(common) >= 2:
        shared = rows.filter(pl.col("backbone").is_in([small, large]), pl.col("encoder").is_in(common))
        band = near_tie_band(shared, **boot)
        for rec in records:
            rec.update(_judge(common, rec["source"], rec["target"], band))
    return records


def transfer_verdicts(
    results: pl.DataFrame,
    *,
    small: str = SMALL,
    large: str = LARGE,
    confidence: float = CONFIDENCE,
    n_boot: int = N_BOOT,
    seed: int = BOOT_SEED,
) -> pl.DataFrame:
    """Per suite and direction: is the source backbone's winner in the target backbone's top tier?

    Two rows per suite, small -> large first. Only encoders with data on both backbones are compared (the
    others are named in `note`). Exact ties for first on the source are all winners (joined by ", ") and
    the ranking transfers only if every one of them is in the target's top tier; a target tier holding
    every shared encoder is NEAR_TIE instead. Fewer than two shared encoders, or a missing backbone, give
    INSUFFICIENT with the reason in `note`. `basis` lists the comparison bases on the target (flags
    single-seed tiers).
    """
    gap = two_backbone_gap(results, small, large)
    boot = {"confidence": confidence, "n_boot": n_boot, "seed": seed}
    records = []
    for suite in plain_suites(results):
        rows = results.filter(pl.col("suite") == suite)
        records += _both_directions(rows, {"suite": suite}, gap, small, large, **boot)
    return pl.DataFrame(records, schema=VERDICT_SCHEMA)


def seed_verdicts(
    results: pl.DataFrame,
    *,
    small: str = SMALL,
    large: str = LARGE,
    confidence: float = CONFIDENCE,
    n_boot: int = N_BOOT,
    seed: int = BOOT_SEED,
) -> pl.DataFrame:
    """Seed-level cells: transfer_verdicts on each seed's rows alone, per suite and direction.

    With one seed per cell the top tier rests on the seed's held-out episodes when rows carry them, and
    is the exact ties of the best otherwise (flagged in `basis`). A seed run on one backbone only gives
    INSUFFICIENT for both directions, as does a table lacking a backbone (every seed of every suite).
    """
    gap = two_backbone_gap(results, small, large)
    boot = {"confidence": confidence, "n_boot": n_boot, "seed": seed}
    valid = control_rows(results, PLAIN).drop_nulls("eval_mse")
    records = []
    for suite in plain_suites(results):
        rows = results.filter(pl.col("suite") == suite)
        in_suite = valid.filter(pl.col("suite") == suite)
        seeds = {b: set(in_suite.filter(pl.col("backbone") == b)["seed"].to_list()) for b in (small, large)}
        for s in sorted(set(in_suite["seed"].to_list())):
            lacking = [backbone_label(b) for b in (small, large) if s not in seeds[b]]
            why = gap or (f"seed {s} not run on {lacking[0]}" if lacking else None)
            where = {"suite": suite, "seed": s}
            records += _both_directions(rows.filter(pl.col("seed") == s), where, why, small, large, **boot)
    return pl.DataFrame(records, schema=SEED_VERDICT_SCHEMA)


def verdict_counts(verdicts: pl.DataFrame, by: Sequence[str] = ()) -> pl.DataFrame:
    """How many comparisons (or seed-level cells) got each verdict (COUNT_COLUMNS), overall or per `by`
    group in first-seen order. `n_judged` leaves out INSUFFICIENT: it is the "of n" in "k of n comparisons",
    since a comparison that could not be made is neither a transfer nor a failure to transfer."""
    v = pl.col("verdict")
    counts = {col: (v == name).sum().cast(pl.Int64) for name, col in COUNT_COLUMNS.items()}
    judged = (v != INSUFFICIENT).sum().cast(pl.Int64)
    if by:
        return verdicts.group_by(list(by), maintain_order=True).agg(**counts, n_judged=judged)
    return verdicts.select(**counts, n_judged=judged)


def _top1(scores: dict[str, float]) -> set[str]:
    low = min(scores.values())
    return {e for e, v in scores.items() if v == low}


PAIRING_SCHEMA = {
    "suite": pl.String,
    "seed": pl.Int64,
    "small_top1": pl.String,
    "large_top1": pl.String,
    "n_common": pl.Int64,
    "disagree": pl.Boolean,
    "note": pl.String,
}


def seed_pairings(results: pl.DataFrame, *, small: str = SMALL, large: str = LARGE) -> pl.DataFrame:
    """Seed-level top-1 agreement: seed s on the small backbone vs seed s on the large one, per suite.

    Top-1 is taken among the encoders that have seed s on both backbones; `disagree` is True when the two
    top-1 sets share no encoder (exact ties count as agreeing if any tied encoder is shared). A seed present
    on one backbone only, or fewer than two shared encoders, gives a row with null `disagree` and a note.
    """
    need = two_backbone_gap(results, small, large)
    if need:
        gaps = [{"suite": s, "note": need} for s in plain_suites(results)]
        return pl.DataFrame(gaps, schema=PAIRING_SCHEMA)
    valid = control_rows(results, PLAIN).drop_nulls("eval_mse")
    records = []
    for suite in plain_suites(results):
        by_backbone = {
            b: {
                (s, e): v
                for s, e, v in valid.filter(pl.col("suite") == suite, pl.col("backbone") == b)
                .select("seed", "encoder", "eval_mse")
                .iter_rows()
            }
            for b in (small, large)
        }
        seeds = {b: {s for s, _ in by_backbone[b]} for b in (small, large)}
        for s in sorted(seeds[small] | seeds[large]):
            rec = {"suite": suite, "seed": s}
            scores = {b: {e: v for (ss, e), v in by_backbone[b].items() if ss == s} for b in (small, large)}
            common = sorted(set(scores[small]) & set(scores[large]))
            rec["n_common"] = len(common)
            if s not in seeds[small] or s not in seeds[large]:
                lacking = small if s not in seeds[small] else large
                rec["note"] = f"seed {s} not run on {backbone_label(lacking)}"
            elif len(common) < 2:
                rec["note"] = f"{len(common)} encoder(s) with seed {s} on both backbones"
            else:
                top = {b: _top1({e: scores[b][e] for e in common}) for b in (small, large)}
                rec.update(
                    small_top1=", ".join(sorted(top[small])),
                    large_top1=", ".join(sorted(top[large])),
                    disagree=top[small].isdisjoint(top[large]),
                )
            records.append(rec)
    return pl.DataFrame(records, schema=PAIRING_SCHEMA)


def seed_disagreement_counts(
    results: pl.DataFrame, *, small: str = SMALL, large: str = LARGE
) -> pl.DataFrame:
    """Per suite: how many seed pairings were comparable, how many disagree on top-1, how many could not
    be paired (`n_unpaired`), and the disagreeing fraction (null when nothing was comparable)."""
    pairs = seed_pairings(results, small=small, large=large)
    d = pl.col("disagree")
    return (
        pairs.group_by("suite")
        .agg(
            n_pairings=d.count().cast(pl.Int64),
            n_disagree=d.sum().cast(pl.Int64),
            n_unpaired=d.null_count().cast(pl.Int64),
        )
        .with_columns(
            fraction_disagree=pl.when(pl.col("n_pairings") > 0)
            .then(pl.col("n_disagree") / pl.col("n_pairings"))
            .otherwise(None)
        )
        .sort("suite")
    )


def kendall_tau(results: pl.DataFrame, *, small: str = SMALL, large: str = LARGE) -> pl.DataFrame:
    """Per suite: Kendall tau-b between the two backbones' mean MSEs over the encoders present on both
    (`n_common`); null with a note when it cannot be computed."""
    schema = {"suite": pl.String, "n_common": pl.Int64, "tau_b": pl.Float64, "note": pl.String}
    need = two_backbone_gap(results, small, large)
    summary = seed_summary(results)
    records = []
    for suite in plain_suites(results):
        rec = {"suite": suite, "n_common": 0, "note": need}
        if not need:
            common, rec["note"] = common_encoders(results.filter(pl.col("suite") == suite), small, large)
            means = {
                b: dict(
                    summary.filter(pl.col("backbone") == b, pl.col("suite") == suite)
                    .select("encoder", "mean")
                    .iter_rows()
                )
                for b in (small, large)
            }
            rec["n_common"] = len(common)
            rec["tau_b"] = tau_b([means[small][e] for e in common], [means[large][e] for e in common])
            if rec["tau_b"] is None:
                why = "fewer than two shared encoders" if len(common) < 2 else "one backbone's means all tie"
                rec["note"] = "; ".join(x for x in (why, rec["note"]) if x)
        records.append(rec)
    return pl.DataFrame(records, schema=schema)
