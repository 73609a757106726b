"""Do two backbones agree beyond the verdicts? Seed-level top-1 agreement (seed s on the smaller backbone
against seed s on the larger one) and Kendall's tau-b between the backbones' mean MSEs, per suite and per
pair of backbones on the ladder (graftcache.analysis.ladder; with two backbones, one pair).
"""

from __future__ import annotations

import polars as pl

from graftcache.analysis.ladder import Ladder, backbone_ladder
from graftcache.analysis.stats import tau_b
from graftcache.analysis.summaries import seed_summary
from graftcache.analysis.table import PLAIN, backbone_label, control_rows, plain_suites
from graftcache.analysis.transfer import common_encoders


def _top1(scores: dict[str, float]) -> set[str]:
    low = min(scores.values())
    return {e for e, v in scores.items() if v == low}


PAIR = {"suite": pl.String, "small": pl.String, "large": pl.String}  # `small`: the pair's smaller backbone
PAIRING_SCHEMA = {
    **PAIR,
    "seed": pl.Int64,
    "small_top1": pl.String,
    "large_top1": pl.String,
    "n_common": pl.Int64,
    "disagree": pl.Boolean,
    "note": pl.String,
}
TAU_SCHEMA = {**PAIR, "n_common": pl.Int64, "tau_b": pl.Float64, "note": pl.String}


def seed_pairings(results: pl.DataFrame, *, ladder: Ladder | None = None) -> pl.DataFrame:
    """Seed-level top-1 agreement per suite and pair: seed s on the smaller backbone vs seed s on the larger.

    Top-1 is taken among the encoders that have seed s on both backbones; `disagree` is True when the two
    top-1 sets share no encoder (exact ties count as agreeing if any tied encoder is shared). A seed present
    on one backbone only, or fewer than two shared encoders, gives a row with null `disagree` and a note.
    No rows with fewer than two backbones.
    """
    ladder = ladder or backbone_ladder(results)
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
            for b in ladder.backbones
        }
        for small, large in ladder.pairs:
            seeds = {b: {s for s, _ in by_backbone[b]} for b in (small, large)}
            for s in sorted(seeds[small] | seeds[large]):
                rec = {"suite": suite, "small": small, "large": large, "seed": s}
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


def seed_disagreement_counts(results: pl.DataFrame, *, ladder: Ladder | None = None) -> pl.DataFrame:
    """Per suite and pair: how many seed pairings were comparable, how many disagree on top-1, how many could
    not be paired (`n_unpaired`), and the disagreeing fraction (null when nothing was comparable)."""
    pairs = seed_pairings(results, ladder=ladder)
    d = pl.col("disagree")
    return (
        pairs.group_by(list(PAIR), maintain_order=True)
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
    )


def kendall_tau(results: pl.DataFrame, *, ladder: Ladder | None = None) -> pl.DataFrame:
    """Per suite and pair: Kendall tau-b between the two backbones' mean MSEs over the encoders present on
    both (`n_common`); null with a note when it cannot be computed. The tau-b matrix of a suite is its rows
    (graftcache.analysis.agreement.tau_matrix)."""
    ladder = ladder or backbone_ladder(results)
    summary = seed_summary(results)
    records = []
    for suite in plain_suites(results):
        means = {
            b: dict(
                summary.filter(pl.col("backbone") == b, pl.col("suite") == suite)
                .select("encoder", "mean")
                .iter_rows()
            )
            for b in ladder.backbones
        }
        for small, large in ladder.pairs:
            rec = {"suite": suite, "small": small, "large": large}
            common, rec["note"] = common_encoders(results.filter(pl.col("suite") == suite), small, large)
            rec["n_common"] = len(common)
            rec["tau_b"] = tau_b([means[small][e] for e in common], [means[large][e] for e in common])
            if rec["tau_b"] is None:
                why = "fewer than two shared encoders" if len(common) < 2 else "one backbone's means all tie"
                rec["note"] = "; ".join(x for x in (why, rec["note"]) if x)
            records.append(rec)
    return pl.DataFrame(records, schema=TAU_SCHEMA)


def tau_matrix(tau: pl.DataFrame, suite: str, backbones: tuple[str, ...]) -> list[list[float | None]]:
    """One suite's Kendall tau-b as a symmetric backbone x backbone matrix in ladder order (1.0 on the
    diagonal, None where it could not be computed)."""
    at = {(r["small"], r["large"]): r["tau_b"] for r in tau.filter(pl.col("suite") == suite).iter_rows(named=True)}
    return [[1.0 if a == b else at.get((a, b), at.get((b, a))) for b in backbones] for a in backbones]
