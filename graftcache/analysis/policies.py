"""A policy is counted once: results rows that hold the same policy are one closed-loop cell, not several.

Some rows differ in a column that does not change what the rolled-out policy computes: a zero-image control never
sees the encoder, so its rows under three encoders are one blind policy, rolled out three times on the same
scenes. Counting such a policy once per row weighs it as several independent policies in every agreement figure,
interval and paired line. Rows name their policy in `policy_id` where the table has the column; a row without it
(older tables, other tools) is its own policy, named by its run_id: `pl.coalesce("policy_id", "run_id")`.

One row per policy stands for it: the first by run_id. Its offline scores are every row's (the rows hold one
trained policy scored on the same frames, so they are equal by construction), and its identity columns
(encoder, seed, run_id) are that row's, with `runs` saying how many rows the policy had.

Its episodes are pooled over its rows, and an episode key (PAIR_KEY, a null perturbation_m read as 0.0: the
official init states) that several of its rows ran is kept once, the first run_id's: the same policy on the same
scene is one observation, so a policy rolled out three times still has as many episodes as scenes. An episode
with another key column null cannot be recognised as a repeat and is kept.
"""

from __future__ import annotations

import polars as pl

from graftcache.analysis.rollouts import PAIR_KEY

#: The results column naming a row's policy, and the column `policies` and `policy_episodes` add with its key
#: (`policy` is taken: it names the backbone's policy)
POLICY_ID, POLICY = "policy_id", "policy_key"
KEY = list(PAIR_KEY)


def policy_of(results: pl.DataFrame) -> pl.Expr:
    """Each results row's policy: its policy_id, or its run_id where the table has no policy_id (or it is null)."""
    run = pl.col("run_id").cast(pl.String)
    return (pl.coalesce(pl.col(POLICY_ID).cast(pl.String), run) if POLICY_ID in results.columns else run).alias(POLICY)


def policies(results: pl.DataFrame) -> pl.DataFrame:
    """One results row per policy (the first by run_id), with `policy_key` and `runs` (its rows in `results`)."""
    keyed = results.with_columns(policy_of(results)).sort("run_id")
    runs = keyed.group_by(POLICY).agg(runs=pl.len())
    return keyed.unique(POLICY, keep="first", maintain_order=True).join(runs, on=POLICY, how="left")


def policy_episodes(results: pl.DataFrame, rollouts: pl.DataFrame) -> pl.DataFrame:
    """`rollouts` (read_rollouts) with each episode's `policy_key`, perturbation_m null read as 0.0, and an episode
    key that several rows of one policy ran kept once (the first run_id's)."""
    keyed = rollouts.join(results.select("run_id", policy_of(results)), on="run_id", how="inner").with_columns(
        pl.col("perturbation_m").fill_null(0.0))
    whole = pl.all_horizontal(pl.col(KEY).is_not_null())
    once = keyed.filter(whole).sort("run_id", maintain_order=True).unique([POLICY, *KEY], keep="first",
                                                                          maintain_order=True)
    return pl.concat([once, keyed.filter(~whole)])
