"""transfer.csv: every transfer verdict of a report as one machine-readable row, for tools and spreadsheets.

Columns (TRANSFER_CSV_COLUMNS): `suite`; `seed` (empty for the verdict pooled over seeds); `source_backbone`,
`target_backbone`; `source_winner` (exact ties for first joined by ";"); `target_top_tier` (names joined by
";", best first); `verdict`, one of graftcache.analysis.VERDICTS. Pooled verdicts come first, then the
seed-level cells, each in the analysis' order (suite, pair on the ladder, smaller -> larger first). Fields a
verdict that could not be reached lacks (winner, tier) are empty.
"""

from __future__ import annotations

import polars as pl

from graftcache import analysis as A

TRANSFER_CSV = "transfer.csv"
TRANSFER_CSV_COLUMNS = (
    "suite", "seed", "source_backbone", "target_backbone", "source_winner", "target_top_tier", "verdict",
)


def _rows(verdicts: pl.DataFrame) -> pl.DataFrame:
    seed = pl.col("seed") if "seed" in verdicts.columns else pl.lit(None, dtype=pl.Int64)
    return verdicts.select(
        "suite",
        seed.alias("seed"),
        source_backbone="source",
        target_backbone="target",
        source_winner=pl.col("source_winner").str.replace_all(", ", ";", literal=True),
        target_top_tier=pl.col("target_band").list.join(";"),
        verdict="verdict",
    )


def transfer_table(a: A.Analysis) -> pl.DataFrame:
    """The rows transfer.csv holds (TRANSFER_CSV_COLUMNS), from an Analysis."""
    return pl.concat([_rows(a.verdicts), _rows(a.seed_verdicts)])
