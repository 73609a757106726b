"""closed_loop.csv: how well each offline score agrees with closed-loop success, one row per (backbone, suite,
score), for tools and spreadsheets; written by `graftcache report --rollouts`.

Columns (CLOSED_LOOP_CSV_COLUMNS): `backbone`, `suite`; `score`, a results column (graftcache.analysis
.CLOSED_LOOP_SCORES); `cells`, the run_ids with rollouts and a finite score; `spearman` and `kendall_tau_b` of
-score against the success rate (positive: lower scores go with more success), `mmrv` (SIMPLER's mean maximum rank
violation, in success-rate units). A figure that is undefined (fewer than 2 cells, every cell with the same
success rate; rho and tau-b also with one score for all) is empty, never a number: the report says why.
"""

from __future__ import annotations

import polars as pl

from graftcache import analysis as A

CLOSED_LOOP_CSV = "closed_loop.csv"
CLOSED_LOOP_CSV_COLUMNS = ("backbone", "suite", "score", "cells", "spearman", "kendall_tau_b", "mmrv")


def closed_loop_table(a: A.Analysis) -> pl.DataFrame:
    """The rows closed_loop.csv holds (CLOSED_LOOP_CSV_COLUMNS), from an Analysis given rollouts."""
    return a.closed_loop.agreement.select(CLOSED_LOOP_CSV_COLUMNS)
