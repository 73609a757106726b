"""The ladder's headline, per suite: does the smallest backbone's winner land in the largest one's top tier,
and where along the ladder (smallest to largest, one rung at a time) does the ranking break?

The ranking *breaks* at the first rung (a backbone and the next larger one) whose upward verdict is "does not
transfer". A near-tie band on a rung separates nothing, so it is neither a transfer nor a break (named in
`steps`), and a rung that could not be judged leaves the question open below it (`break_at` is null and
`open_rungs` counts such rungs).
"""

from __future__ import annotations

import polars as pl

from graftcache.analysis.ladder import Ladder
from graftcache.analysis.transfer import DOES_NOT_TRANSFER, INSUFFICIENT

HEADLINE_SCHEMA = {
    "suite": pl.String,
    "smallest": pl.String,
    "largest": pl.String,
    "smallest_winner": pl.String,
    "largest_top_tier": pl.List(pl.String),
    "verdict": pl.String,           # smallest -> largest
    "steps": pl.List(pl.String),    # upward verdict of each rung, bottom to top
    "break_at": pl.String,          # "<smaller> -> <larger>" of the first rung that does not transfer, or null
    "open_rungs": pl.Int64,         # rungs below the break (all of them without one) with insufficient data
}


def ladder_headline(verdicts: pl.DataFrame, ladder: Ladder) -> pl.DataFrame:
    """One row per suite of `verdicts` (graftcache.analysis.transfer_verdicts on this ladder); none with fewer
    than two backbones."""
    if ladder.gap:
        return pl.DataFrame(schema=HEADLINE_SCHEMA)
    smallest, largest = ladder.backbones[0], ladder.backbones[-1]
    up = {(r["suite"], r["source"], r["target"]): r for r in verdicts.iter_rows(named=True)}
    records = []
    for suite in dict.fromkeys(verdicts["suite"].to_list()):
        ends = up[suite, smallest, largest]
        steps = [up[suite, a, b]["verdict"] for a, b in ladder.steps]
        broken = next((i for i, v in enumerate(steps) if v == DOES_NOT_TRANSFER), None)
        below = steps if broken is None else steps[:broken]
        records.append({
            "suite": suite, "smallest": smallest, "largest": largest, "smallest_winner": ends["source_winner"],
            "largest_top_tier": ends["target_band"], "verdict": ends["verdict"], "steps": steps,
            "break_at": None if broken is None else " -> ".join(ladder.steps[broken]),
            "open_rungs": sum(v == INSUFFICIENT for v in below),
        })
    return pl.DataFrame(records, schema=HEADLINE_SCHEMA)
