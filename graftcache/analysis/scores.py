"""Which score ranks the encoders: offline action MSE over the whole chunk (`mse`, the default) or
critical-interval MSE (`ci-mse`, graftcache/critical.py), and where the two rankings disagree.

Every question is asked of `eval_mse` and its per-episode list; `scored` puts the chosen score's columns
there, so the bootstrap, tiers, verdicts and controls rank by it unchanged. A held-out episode without a
critical step has no CI-MSE; it is left out of its row's episode list (a row without any then bootstraps
over seeds only), never counted as zero.
"""

from __future__ import annotations

import polars as pl

from graftcache.analysis.stats import tau_b
from graftcache.analysis.summaries import rankings
from graftcache.analysis.table import EPISODE_COLUMN, GROUP, PLAIN, control_rows
from graftcache.errors import GraftcacheError

#: score name -> (cell column, per-episode list column)
SCORES: dict[str, tuple[str, str]] = {
    "mse": ("eval_mse", EPISODE_COLUMN),
    "ci-mse": ("eval_ci_mse", "eval_ci_mse_episodes"),
}
SCORE_LABELS = {"mse": "offline action MSE", "ci-mse": "critical-interval MSE (CI-MSE)"}


def has_score(results: pl.DataFrame, score: str) -> bool:
    """Whether any plain-graft row carries a value of the score."""
    column = SCORES[score][0]
    return column in results.columns and bool(control_rows(results, PLAIN)[column].drop_nulls().len())


def scored(results: pl.DataFrame, score: str) -> pl.DataFrame:
    """The table with `score` in eval_mse and its per-episode values in EPISODE_COLUMN (a conformed table:
    every SCHEMA column present). A score no plain-graft row carries is a GraftcacheError."""
    if score not in SCORES:
        raise GraftcacheError(f"score {score!r}: choose one of {', '.join(SCORES)}")
    column, episodes = SCORES[score]
    if score == "mse":
        return results
    if not has_score(results, score):
        raise GraftcacheError(f"no plain-graft row carries {column} (rows written before CI-MSE, or by another "
                              "tool): rank by --score mse")
    per_episode = pl.col(episodes).list.drop_nulls()
    return results.with_columns(
        eval_mse=pl.col(column),
        **{EPISODE_COLUMN: pl.when(per_episode.list.len() > 0).then(per_episode).otherwise(None)},
    )


DISAGREEMENT_SCHEMA = {
    "backbone": pl.String,
    "suite": pl.String,
    "mse_top1": pl.String,
    "ci_mse_top1": pl.String,
    "n_common": pl.Int64,
    "tau_b": pl.Float64,
    "moved": pl.List(pl.String),  # "encoder: rank under mse -> rank under ci-mse", for every rank that differs
    "same_top1": pl.Boolean,
}


def score_disagreement(results: pl.DataFrame) -> pl.DataFrame:
    """Per (backbone, suite): each score's top-1 (ties joined by ", "), Kendall tau-b between the two
    rankings' means over the encoders ranked by both, and every encoder whose rank differs. Empty when the
    table holds no CI-MSE."""
    if not has_score(results, "ci-mse"):
        return pl.DataFrame(schema=DISAGREEMENT_SCHEMA)
    ranks = {s: rankings(scored(results, s)).drop_nulls("mean") for s in SCORES}
    records = []
    for key, mse in ranks["mse"].group_by(GROUP, maintain_order=True):
        ci = ranks["ci-mse"].filter(pl.col("backbone") == key[0], pl.col("suite") == key[1])
        a = {e: (r, m) for e, r, m in mse.select("encoder", "rank", "mean").iter_rows()}
        b = {e: (r, m) for e, r, m in ci.select("encoder", "rank", "mean").iter_rows()}
        common = sorted(set(a) & set(b))
        top = {name: ", ".join(sorted(e for e in common if side[e][0] == min(side[c][0] for c in common)))
               for name, side in (("mse", a), ("ci", b))} if common else {"mse": None, "ci": None}
        records.append({
            "backbone": key[0], "suite": key[1], "mse_top1": top["mse"], "ci_mse_top1": top["ci"],
            "n_common": len(common), "tau_b": tau_b([a[e][1] for e in common], [b[e][1] for e in common]),
            "moved": [f"{e}: {a[e][0]} -> {b[e][0]}" for e in common if a[e][0] != b[e][0]],
            "same_top1": None if not common else top["mse"] == top["ci"],
        })
    return pl.DataFrame(records, schema=DISAGREEMENT_SCHEMA)
