"""Do the two backbones agree beyond the verdicts? Seed-level top-1 agreement (seed s on the small backbone
against seed s on the large one) and Kendall's tau-b between the backbones' mean MSEs, per suite.
"""

from __future__ import annotations

import polars as pl

from graftcache.analysis.stats import tau_b
from graftcache.analysis.summaries import seed_summary
from graftcache.analysis.table import LARGE, PLAIN, SMALL, backbone_label, control_rows, plain_suites
from graftcache.analysis.transfer import common_encoders, two_backbone_gap


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
