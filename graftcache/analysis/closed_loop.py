"""Offline scores against closed-loop success: does a lower offline score go with a higher success rate?

A *cell* here is one results row with rollouts, i.e. one run_id (one seed of one encoder or control): its success
rate over its episodes, with a 95% Wilson score interval. Per (backbone, suite) and offline score
(CLOSED_LOOP_SCORES), the agreement between the score and the success rate over the cells: Spearman's rho,
Kendall's tau-b and SIMPLER's mean maximum rank violation (MMRV; Li et al. 2024, arXiv 2405.05941).

Agreement is computed over run_ids, not over seed means: a run_id is one trained projector, the very policy that
was scored offline and rolled out, so its score and its success rate are one paired measurement. Averaging seeds
first would pair a mean score with a mean success and hide the seed noise an offline score must see through.

Signs: the proxy is -score (lower is better), so rho and tau-b are positive where lower scores go with higher
success, and MMRV, an error in success-rate units, is 0 where no pair is ordered against success. They are
undefined (null, and a `note` says why) with fewer than 2 cells and where every cell has the same success rate
(e.g. all 0: there is no order to agree with); rho and tau-b also where every cell has the same score. A
non-finite or null score leaves its cell out of that score's agreement.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from statistics import NormalDist

import numpy as np
import polars as pl

from graftcache.analysis.stats import tau_b
from graftcache.analysis.table import GROUP

#: The offline scores set against success, each a results column (lower is better)
CLOSED_LOOP_SCORES = ("eval_mse", "eval_ci_mse", "eval_mse_arm", "eval_mse_gripper")
#: The two-sided 95% normal quantile of the Wilson interval
Z95 = NormalDist().inv_cdf(0.975)

CELL_SCHEMA = {
    "backbone": pl.String, "suite": pl.String, "encoder": pl.String, "control": pl.String, "seed": pl.Int64,
    "run_id": pl.String, "episodes": pl.Int64, "successes": pl.Int64, "success_rate": pl.Float64,
    "ci_low": pl.Float64, "ci_high": pl.Float64, **dict.fromkeys(CLOSED_LOOP_SCORES, pl.Float64),
}
AGREEMENT_SCHEMA = {
    "backbone": pl.String, "suite": pl.String, "score": pl.String, "cells": pl.Int64, "spearman": pl.Float64,
    "kendall_tau_b": pl.Float64, "mmrv": pl.Float64, "note": pl.String,
}


@dataclass(frozen=True)
class ClosedLoop:
    """What the report shows of rollouts: one row per cell (CELL_SCHEMA), one per (backbone, suite, score)
    (AGREEMENT_SCHEMA)."""

    cells: pl.DataFrame
    agreement: pl.DataFrame


def wilson(successes: int, n: int, z: float = Z95) -> tuple[float, float]:
    """Wilson score interval of a success rate: unlike the normal interval it stays inside [0, 1] and is not a
    point at 0 or n successes, which is where tiny policies' rates sit. The bounds hold the rate itself: at 0 or n
    successes the formula's bound is the rate exactly, which floats miss by an ulp (0 of 10 gave a low bound of
    2.8e-17, above the rate: a negative error bar, which matplotlib refuses)."""
    p = successes / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z / (1 + z * z / n) * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n))
    return max(0.0, min(p, centre - half)), min(1.0, max(p, centre + half))


def spearman(x: Sequence[float], y: Sequence[float]) -> float | None:
    """Spearman's rho: Pearson's correlation of the average ranks (ties share their mean rank). None with fewer
    than two items or when either side is all ties."""
    if len(x) < 2:
        return None
    rx, ry = (pl.Series(v, dtype=pl.Float64).rank("average").to_numpy() for v in (x, y))
    if np.ptp(rx) == 0 or np.ptp(ry) == 0:
        return None
    return float(np.corrcoef(rx, ry)[0, 1])


def mmrv(score: Sequence[float], success: Sequence[float]) -> float:
    """MMRV = (1/N) sum_i max_j |R_i - R_j| [(S_i < S_j) != (R_i < R_j)], with the proxy S = -score and R the
    success rates: each cell's worst ordering error, weighted by the success it misjudges, averaged."""
    s, r = -np.asarray(score, dtype=np.float64), np.asarray(success, dtype=np.float64)
    violated = (s[:, None] < s[None, :]) != (r[:, None] < r[None, :])
    return float((np.abs(r[:, None] - r[None, :]) * violated).max(axis=1).mean())


def success_cells(results: pl.DataFrame, rollouts: pl.DataFrame) -> pl.DataFrame:
    """Per results row with rollouts (rollouts: run_id, success per episode), its success rate and Wilson
    interval beside its offline scores, in (backbone, suite, encoder, control, seed) order."""
    per_run = rollouts.group_by("run_id").agg(episodes=pl.len(), successes=pl.col("success").sum())
    cells = results.join(per_run, on="run_id", how="inner").sort("backbone", "suite", "encoder", "control", "seed")
    bounds = [wilson(k, n) for k, n in cells.select("successes", "episodes").iter_rows()]
    return cells.with_columns(
        success_rate=pl.col("successes") / pl.col("episodes"),
        ci_low=pl.Series([lo for lo, _ in bounds], dtype=pl.Float64),
        ci_high=pl.Series([hi for _, hi in bounds], dtype=pl.Float64),
    ).select([pl.col(c).cast(t) for c, t in CELL_SCHEMA.items()])


def _why_undefined(score: str, values: np.ndarray, rates: np.ndarray) -> str | None:
    """Why no agreement figure can be given over these cells, or None."""
    if len(values) == 0:
        return f"no cell with rollouts has a finite {score}"
    if len(values) == 1:
        return "1 cell: agreement needs 2 or more"
    if np.ptp(rates) == 0:
        return f"every cell's success rate is {rates[0]:.0%}: no order to agree with"
    return None


def agreement(cells: pl.DataFrame) -> pl.DataFrame:
    """Per (backbone, suite) and CLOSED_LOOP_SCORES score: how many cells have it, and rho, tau-b (both of -score
    against success) and MMRV over them, null where undefined (see the module docstring), `note` saying why."""
    records = []
    for (backbone, suite), group in cells.group_by(GROUP, maintain_order=True):
        for score in CLOSED_LOOP_SCORES:
            valid = group.filter(pl.col(score).is_finite())
            values, rates = valid[score].to_numpy(), valid["success_rate"].to_numpy()
            note = _why_undefined(score, values, rates)
            rho = tau = worst = None
            if note is None:
                rho, tau, worst = spearman(-values, rates), tau_b(-values, rates), mmrv(values, rates)
                if rho is None:
                    note = f"every cell has the same {score}: rho and tau-b undefined"
            records.append({"backbone": backbone, "suite": suite, "score": score, "cells": len(values),
                            "spearman": rho, "kendall_tau_b": tau, "mmrv": worst, "note": note})
    return pl.DataFrame(records, schema=AGREEMENT_SCHEMA)


def closed_loop(results: pl.DataFrame, rollouts: pl.DataFrame) -> ClosedLoop:
    """Cells and agreement from a conformed results table (every SCHEMA column, scores unreplaced) and rollouts
    (graftcache.analysis.rollouts.read_rollouts)."""
    cells = success_cells(results, rollouts)
    return ClosedLoop(cells, agreement(cells))
