"""closed_loop.csv and pairwise.csv, for tools and spreadsheets; written by `graftcache report --rollouts`.

closed_loop.csv: how well each offline score agrees with each closed-loop measure, one row per (backbone, suite,
cells_of, score, measure). Columns (CLOSED_LOOP_CSV_COLUMNS, typed by CLOSED_LOOP_CSV_SCHEMA): `backbone`,
`suite`; `cells_of`, which cells the agreement is over: "candidates" (the plain grafts: does the score order the
encoders as the closed loop does?) or "with controls" (every distinct policy: does looking help?); `score`, a
results column (graftcache.analysis.CLOSED_LOOP_SCORES); `measure`, a closed-loop measure
(graftcache.analysis.MEASURES: `success` and the graded ones); `cells`, the policies with rollouts, a finite score
and the measure recorded; `spearman` and `kendall_tau_b` of -score against the measure oriented so that higher is
better (positive: lower scores go with a better closed loop, for every measure), `mmrv` (SIMPLER's mean maximum
rank violation, in the measure's units: a rate, metres or a fraction); each with `_low` and `_high`, its 95%
interval from the bootstrap over cells and their episodes (graftcache.analysis.closed_loop_boot), which holds the
figure; `replicates`, how many of the bootstrap's graftcache.analysis.N_BOOT replicates the intervals were taken
over (those in which the drawn cells did not all tie). A figure that is undefined (fewer than 2 cells, every cell
with the same value of the measure, a graded measure that no episode records; rho and tau-b also with one score
for all) is empty, never a number: the report says why.

pairwise.csv: one row per (backbone, suite, measure, pair of candidate encoders), the columns of
graftcache.analysis.PAIRWISE_SCHEMA (PAIRWISE_CSV_COLUMNS, graftcache.analysis.pairwise says what each holds),
`note` included: it says why a figure or verdict is empty.
"""

from __future__ import annotations

import polars as pl

from graftcache import analysis as A

CLOSED_LOOP_CSV, PAIRWISE_CSV = "closed_loop.csv", "pairwise.csv"
CLOSED_LOOP_CSV_SCHEMA: dict[str, pl.DataType] = {
    c: t for c, t in A.AGREEMENT_SCHEMA.items() if c != "note"
}
CLOSED_LOOP_CSV_COLUMNS = tuple(CLOSED_LOOP_CSV_SCHEMA)
PAIRWISE_CSV_SCHEMA: dict[str, pl.DataType] = dict(A.PAIRWISE_SCHEMA)
PAIRWISE_CSV_COLUMNS = tuple(PAIRWISE_CSV_SCHEMA)


def closed_loop_table(a: A.Analysis) -> pl.DataFrame:
    """The rows closed_loop.csv holds (CLOSED_LOOP_CSV_COLUMNS), from an Analysis given rollouts."""
    return a.closed_loop.agreement.select([pl.col(c).cast(t) for c, t in CLOSED_LOOP_CSV_SCHEMA.items()])


def pairwise_table(a: A.Analysis) -> pl.DataFrame:
    """The rows pairwise.csv holds (PAIRWISE_CSV_COLUMNS), from an Analysis given rollouts."""
    return a.closed_loop.pairwise.select([pl.col(c).cast(t) for c, t in PAIRWISE_CSV_SCHEMA.items()])
