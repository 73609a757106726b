"""The bootstrap behind the closed-loop agreement intervals: over cells (policies) and, within each drawn cell,
its episodes; and the agreement statistics over many replicates at once.

Why two levels: an agreement figure is a statement about the policies in hand, and it moves both when other
policies of the same kind are drawn (a handful of seeds per encoder) and when a policy's few episodes are
redrawn (4-10 per cell in the closed-loop demo). An interval over episodes alone holds the policies fixed and
misses the first, which is the larger one where a few cells decide the order. A replicate draws as many cells as
there are with replacement, then each drawn cell's episodes with replacement (a cell drawn twice draws its
episodes twice, independently), recomputes each drawn cell's mean, and then rho, tau-b and MMRV over the drawn
cells against their offline scores.

Why a symmetric interval, figure +- the `LEVEL` quantile of |replicate - figure|, rather than the replicates'
percentiles: redrawing episodes adds their noise to the noise already in each observed mean, and noise blurs an
order more often than it sharpens one, so the replicates lean towards weaker agreement. Where the cells are
ordered almost perfectly every replicate can lie on one side of the figure and a percentile interval then misses
it (an MMRV of 0.031 m with a percentile interval of [0.038, 0.064]): an interval that does not hold its own
figure is not an interval for that figure. The symmetric interval holds it by construction, is as wide as the
replicates' spread around it, and is clipped to the statistic's range (rho and tau-b in [-1, 1], MMRV >= 0).

Why N_BOOT = 1000, declared once: the interval reads the 950th of 1000 sorted distances, whose Monte Carlo error
is about 0.01-0.02 on a correlation, well below the width that a few cells and episodes give (tenths); 1000 is
the usual count for bootstrap intervals (Efron and Tibshirani 1993, ch. 13), and a whole report's closed-loop
bootstrap stays within seconds.

Every generator (graftcache.analysis.stats.generator) is seeded by (seed, what is resampled), never by
iteration order, and the caller orders cells by their policy and each cell's episodes by value, so intervals do
not move when cells or rows are reordered.
"""

from __future__ import annotations

import numpy as np

#: Bootstrap replicates of every closed-loop interval (see the module docstring for why 1000).
N_BOOT = 1000
#: The two-sided coverage of every closed-loop interval.
LEVEL = 0.95


def resampled_means(values: np.ndarray, rng: np.random.Generator, n_boot: int = N_BOOT) -> np.ndarray:
    """n_boot means of `values` redrawn with replacement (as many as there are)."""
    return values[rng.integers(0, len(values), size=(n_boot, len(values)))].mean(axis=1)


def interval(replicates: np.ndarray) -> tuple[float | None, float | None]:
    """The LEVEL percentile interval of the replicates (None, None without any): for a mean, whose replicates
    centre on it."""
    if not len(replicates):
        return None, None
    tail = 100 * (1 - LEVEL) / 2
    lo, hi = np.percentile(replicates, [tail, 100 - tail])
    return float(lo), float(hi)


def symmetric_interval(point: float, replicates: np.ndarray, low: float, high: float) -> tuple[float, float]:
    """point +- the LEVEL quantile of the replicates' distance from it, clipped to [low, high]: an interval that
    holds its figure (the module docstring says why); the point alone without a finite replicate."""
    spread = np.abs(replicates[np.isfinite(replicates)] - point)
    half = float(np.quantile(spread, LEVEL)) if len(spread) else 0.0
    return max(low, point - half), min(high, point + half)


def two_level(values: list[np.ndarray], rng: np.random.Generator,
              n_boot: int = N_BOOT) -> tuple[np.ndarray, np.ndarray]:
    """Replicates over cells and their episodes: the drawn cells' indices and their means, both (n_boot, cells).
    `values` holds each cell's episode values; a replicate draws len(values) cells with replacement, then each
    drawn cell's episodes with replacement."""
    picks = rng.integers(0, len(values), size=(n_boot, len(values)))
    means = np.empty(picks.shape)
    for cell, episodes in enumerate(values):
        drawn = picks == cell
        means[drawn] = resampled_means(episodes, rng, int(drawn.sum()))
    return picks, means


def average_ranks(rows: np.ndarray) -> np.ndarray:
    """Each row's average ranks (1 = smallest; ties share the mean of their ranks): an item's rank is the
    number of items below it plus the mean position among its ties, (ties + 1) / 2."""
    below = (rows[:, None, :] < rows[:, :, None]).sum(axis=2)
    ties = (rows[:, None, :] == rows[:, :, None]).sum(axis=2)
    return below + (ties + 1) / 2


def spearman_rows(x: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """Spearman's rho of each row of `x` against the same row of `rows` (Pearson's r of average ranks); NaN where
    a side is all ties."""
    rx, ry = average_ranks(x), average_ranks(rows)
    cx, cy = rx - rx.mean(axis=1, keepdims=True), ry - ry.mean(axis=1, keepdims=True)
    denom = np.sqrt((cx * cx).sum(axis=1) * (cy * cy).sum(axis=1))
    with np.errstate(invalid="ignore", divide="ignore"):
        return (cx * cy).sum(axis=1) / denom


def tau_b_rows(x: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """Kendall's tau-b of each row of `x` against the same row of `rows`, as graftcache.analysis.stats.tau_b;
    NaN where a side is all ties."""
    i, j = np.triu_indices(x.shape[1], 1)
    sx, sy = np.sign(x[:, i] - x[:, j]), np.sign(rows[:, i] - rows[:, j])
    denom = np.sqrt(np.count_nonzero(sx, axis=1) * np.count_nonzero(sy, axis=1).astype(np.float64))
    with np.errstate(invalid="ignore", divide="ignore"):
        return (sx * sy).sum(axis=1) / denom


def mmrv_rows(score: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """MMRV (graftcache.analysis.closed_loop.mmrv) of each row of `score` (lower is better) against the same row
    of `rows` (higher is better)."""
    s = -score
    violated = (s[:, :, None] < s[:, None, :]) != (rows[:, :, None] < rows[:, None, :])
    return (np.abs(rows[:, :, None] - rows[:, None, :]) * violated).max(axis=2).mean(axis=1)
