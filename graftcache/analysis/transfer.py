"""Does the encoder ranking transfer between backbones? Verdicts in both directions for every pair of
backbones, per suite and per seed-level cell, and their counts (top-1 agreement and Kendall's tau-b:
graftcache.analysis.agreement).

A *comparison* is (suite, direction); for each pair of backbones on the ladder (graftcache.analysis.ladder,
smaller first) the directions are smaller -> larger (is the smaller backbone's winner in the larger one's top
tier?) and larger -> smaller. With the paper's two backbones that is small -> large and back. A *seed-level
cell* repeats the test on one seed's rows alone, so 2 suites x 3 seeds give 12 cells against 4 comparisons,
the paper's "k of n" counts.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import polars as pl

from graftcache.analysis.ladder import Ladder, backbone_ladder
from graftcache.analysis.stats import BootSettings
from graftcache.analysis.summaries import near_tie_band
from graftcache.analysis.table import PLAIN, backbone_label, control_rows, plain_suites

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
    rows: pl.DataFrame, where: dict[str, Any], gap: str | None, small: str, large: str, boot: BootSettings
) -> list[dict[str, Any]]:
    """The small -> large and large -> small records of one pair for one suite's rows (or one seed's):
    "insufficient data" with the reason in `note` when `gap` says why, or fewer than two encoders are shared."""
    common, note = ([], gap) if gap else common_encoders(rows, small, large)
    if not gap and len(common) < 2:
        note = "; ".join(x for x in (f"{len(common)} encoder(s) on both backbones", note) if x)
    records = [
        {**where, "source": s, "target": t, "n_common": len(common), "verdict": INSUFFICIENT, "note": note}
        for s, t in ((small, large), (large, small))
    ]
    if len(common) >= 2:
        shared = rows.filter(pl.col("backbone").is_in([small, large]), pl.col("encoder").is_in(common))
        band = near_tie_band(shared, boot=boot)
        for rec in records:
            rec.update(_judge(common, rec["source"], rec["target"], band))
    return records


def transfer_verdicts(
    results: pl.DataFrame, *, ladder: Ladder | None = None, boot: BootSettings = BootSettings()
) -> pl.DataFrame:
    """Per suite, pair of backbones and direction: is the source backbone's winner in the target's top tier?

    Per suite, the ladder's pairs (graftcache.analysis.ladder.Ladder.pairs; the table's own ladder when none
    is given), each as smaller -> larger then larger -> smaller: two rows per suite with two backbones, none
    with fewer (Ladder.gap says why). Only encoders with data on both backbones of a pair are compared (the
    others are named in `note`). Exact ties for first on the source are all winners (joined by ", ") and
    the ranking transfers only if every one of them is in the target's top tier; a target tier holding
    every shared encoder is NEAR_TIE instead. Fewer than two shared encoders give INSUFFICIENT with the
    reason in `note`. `basis` lists the comparison bases on the target (flags single-seed tiers).
    """
    ladder = ladder or backbone_ladder(results)
    records = []
    for suite in plain_suites(results):
        rows = results.filter(pl.col("suite") == suite)
        for small, large in ladder.pairs:
            records += _both_directions(rows, {"suite": suite}, None, small, large, boot)
    return pl.DataFrame(records, schema=VERDICT_SCHEMA)


def seed_verdicts(
    results: pl.DataFrame, *, ladder: Ladder | None = None, boot: BootSettings = BootSettings()
) -> pl.DataFrame:
    """Seed-level cells: transfer_verdicts on each seed's rows alone, per suite, pair and direction.

    With one seed per cell the top tier rests on the seed's held-out episodes when rows carry them, and
    is the exact ties of the best otherwise (flagged in `basis`). The seeds of a pair are those either of its
    backbones ran in the suite; a seed run on one of them only gives INSUFFICIENT for both directions.
    """
    ladder = ladder or backbone_ladder(results)
    valid = control_rows(results, PLAIN).drop_nulls("eval_mse")
    records = []
    for suite in plain_suites(results):
        rows = results.filter(pl.col("suite") == suite)
        in_suite = valid.filter(pl.col("suite") == suite)
        seeds = {b: set(in_suite.filter(pl.col("backbone") == b)["seed"].to_list()) for b in ladder.backbones}
        for small, large in ladder.pairs:
            for s in sorted(seeds[small] | seeds[large]):
                lacking = [backbone_label(b) for b in (small, large) if s not in seeds[b]]
                why = f"seed {s} not run on {lacking[0]}" if lacking else None
                where = {"suite": suite, "seed": s}
                records += _both_directions(rows.filter(pl.col("seed") == s), where, why, small, large, boot)
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
