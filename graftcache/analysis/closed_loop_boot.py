"""The episode bootstrap behind the closed-loop intervals: resample each cell's episodes, recompute its
measure, recompute the agreement statistics; and the same statistics over many replicates at once.

Why episodes, and within each cell: a cell's closed-loop value is a mean over a handful of episodes (4-10 in the
closed-loop demo), and that is where its noise is; the cells themselves are the fixed set of policies that were
scored offline, so they are not resampled. A replicate redraws every cell's episodes with replacement (as many
as it has), recomputes every cell's mean, and then rho, tau-b and MMRV over the cells.

What the 95% percentile interval says: how far the figure would move over reruns with as many episodes per cell,
if each cell's true value were its observed mean. Redrawing episodes adds their noise on top of the noise already
in each observed mean, and noise blurs an order more often than it sharpens one, so the replicates lean towards
weaker agreement (rho, tau-b lower, MMRV higher): where the cells are ordered almost perfectly the interval can lie
just below rho (above MMRV) instead of around it. That is the figure's fragility under episode noise, not an
error; more episodes per cell narrow it and bring it back around the point.

Why N_BOOT = 1000, declared once: the 95% percentile interval reads the 25th and 975th of the sorted replicates,
whose Monte Carlo error at 1000 replicates is about 0.01-0.02 on a correlation, well below the width that a few
episodes per cell give (tenths); 1000 is the usual count for percentile intervals (Efron and Tibshirani 1993,
ch. 13), and a whole report's closed-loop bootstrap (every backbone, suite, score and measure) stays near a second.

Every generator (graftcache.analysis.stats.generator, as the offline bootstrap's) is seeded by (seed, what is
resampled), never by iteration order, so intervals do not move when cells or rows are reordered.
"""

from __future__ import annotations

import numpy as np

#: Bootstrap replicates of every closed-loop interval (see the module docstring for why 1000).
N_BOOT = 1000
#: The two-sided percentile interval's coverage.
LEVEL = 0.95


def resampled_means(values: np.ndarray, rng: np.random.Generator, n_boot: int = N_BOOT) -> np.ndarray:
    """n_boot means of `values` redrawn with replacement (as many as there are): one cell's measure per
    replicate."""
    return values[rng.integers(0, len(values), size=(n_boot, len(values)))].mean(axis=1)


def interval(replicates: np.ndarray) -> tuple[float | None, float | None]:
    """The 95% percentile interval of the replicates (None, None without any)."""
    if not len(replicates):
        return None, None
    tail = 100 * (1 - LEVEL) / 2
    lo, hi = np.percentile(replicates, [tail, 100 - tail])
    return float(lo), float(hi)


def average_ranks(rows: np.ndarray) -> np.ndarray:
    """Each row's average ranks (1 = smallest; ties share the mean of their ranks): an item's rank is the
    number of items below it plus the mean position among its ties, (ties + 1) / 2."""
    below = (rows[:, None, :] < rows[:, :, None]).sum(axis=2)
    ties = (rows[:, None, :] == rows[:, :, None]).sum(axis=2)
    return below + (ties + 1) / 2


def spearman_rows(x: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """Spearman's rho of `x` against each row of `rows` (Pearson's r of average ranks); NaN where a side is all
    ties."""
    rx = average_ranks(x[None, :])[0]
    ry = average_ranks(rows)
    cx, cy = rx - rx.mean(), ry - ry.mean(axis=1, keepdims=True)
    denom = np.sqrt((cx * cx).sum() * (cy * cy).sum(axis=1))
    with np.errstate(invalid="ignore", divide="ignore"):
        return (cy @ cx) / denom


def tau_b_rows(x: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """Kendall's tau-b of `x` against each row of `rows`, as graftcache.analysis.stats.tau_b; NaN where a side
    is all ties."""
    i, j = np.triu_indices(len(x), 1)
    sx, sy = np.sign(x[i] - x[j]), np.sign(rows[:, i] - rows[:, j])
    denom = np.sqrt(float(np.count_nonzero(sx)) * np.count_nonzero(sy, axis=1))
    with np.errstate(invalid="ignore", divide="ignore"):
        return (sy @ sx) / denom


def mmrv_rows(score: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """MMRV (graftcache.analysis.closed_loop.mmrv) of `score` (lower is better) against each row of `rows`
    (higher is better)."""
    s = -score
    violated = (s[:, None] < s[None, :])[None] != (rows[:, :, None] < rows[:, None, :])
    return (np.abs(rows[:, :, None] - rows[:, None, :]) * violated).max(axis=2).mean(axis=1)
