"""The statistics behind every comparison: the seed (and episode) bootstrap, and Kendall's tau-b.

The method is stated once, in the graftcache.analysis docstring; this module implements it.
"""

from __future__ import annotations

import math
import zlib
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import polars as pl

from graftcache.analysis.table import CELL, EPISODE_COLUMN, control_rows
from graftcache.checks import FRACTION, NON_NEGATIVE, POSITIVE
from graftcache.settings import Checked, setting


@dataclass(frozen=True)
class BootSettings(Checked):
    """How every top tier and control comparison is bootstrapped: the one home of these defaults, passed
    whole from the report and notebook down to each question so that no function restates them."""

    confidence: float = setting(0.95, rule=FRACTION)  # one-sided: separable when P(worse) >= confidence
    n_boot: int = setting(2000, rule=POSITIVE)  # replicates per cell
    seed: int = setting(0, rule=NON_NEGATIVE)  # with the cell's name, seeds each cell's generator

# What a comparison's uncertainty rests on (the `basis` column); anything but SOLID_BASES is flagged.
BASIS_SEEDS = "seeds"
BASIS_SEEDS_EPISODES = "seeds+episodes"
BASIS_EPISODES_ONE_SEED = "episodes (single seed)"
BASIS_EXACT_TIES = "exact ties only (single seed)"
BASIS_ONE_SIDE_ONE_SEED = "seeds (one side single seed)"
BASIS_MISSING = "missing"
SOLID_BASES = (BASIS_SEEDS, BASIS_SEEDS_EPISODES)


@dataclass(frozen=True)
class Cell:
    """Valid replicates of one cell: seed-level MSEs, and per-seed episode MSEs when every row has them."""

    values: np.ndarray
    episodes: tuple[np.ndarray, ...] | None


def cells_of(rows: pl.DataFrame) -> dict[tuple[str, ...], Cell]:
    """(backbone, suite, encoder) -> Cell over the rows' valid eval_mse, seeds ascending."""
    rows = rows.drop_nulls("eval_mse")
    has_episodes = EPISODE_COLUMN in rows.columns
    cells: dict[tuple[str, ...], Cell] = {}
    for key, group in rows.sort("seed").group_by(CELL, maintain_order=True):
        episodes = None
        if has_episodes:
            lists = [np.asarray(v if v is not None else [], dtype=np.float64) for v in group[EPISODE_COLUMN]]
            if all(len(e) and np.isfinite(e).all() for e in lists):
                episodes = tuple(lists)
        cells[tuple(key)] = Cell(group["eval_mse"].to_numpy().astype(np.float64), episodes)
    return cells


def generator(seed: int, *key: str) -> np.random.Generator:
    """A generator that depends only on the bootstrap seed and what it resamples (a cell; a run_id and a measure),
    not on iteration order."""
    return np.random.default_rng(np.random.SeedSequence([seed, zlib.crc32("\x1f".join(key).encode())]))


def _boot_means(cell: Cell, rng: np.random.Generator, n_boot: int, with_episodes: bool) -> np.ndarray:
    """n_boot bootstrap replicates of the cell's mean MSE: resample seeds, then (optionally) each drawn
    seed's episodes, so both sources of noise widen the distribution."""
    n = len(cell.values)
    pick = rng.integers(0, n, size=(n_boot, n))
    if not with_episodes or cell.episodes is None:
        return cell.values[pick].mean(axis=1)
    per_seed = np.stack(
        [e[rng.integers(0, len(e), size=(n_boot, n, len(e)))].mean(axis=2) for e in cell.episodes]
    )
    return per_seed[pick, np.arange(n_boot)[:, None], np.arange(n)[None, :]].mean(axis=1)


def _basis(n_a: int, n_b: int, episodes: bool) -> str:
    """What a comparison's uncertainty rests on, from the two cells' seed counts."""
    lo, hi = min(n_a, n_b), max(n_a, n_b)
    if episodes:
        return BASIS_SEEDS_EPISODES if lo >= 2 else BASIS_EPISODES_ONE_SEED
    if lo >= 2:
        return BASIS_SEEDS
    return BASIS_EXACT_TIES if hi == 1 else BASIS_ONE_SIDE_ONE_SEED


class Bootstrap:
    """Bootstrap replicates per cell, drawn once and reused for every comparison that involves the cell."""

    def __init__(self, results: pl.DataFrame, control: str, settings: BootSettings) -> None:
        self.cells = cells_of(control_rows(results, control))
        self.tag, self.settings = control, settings
        self._cache: dict[tuple[tuple[str, ...], bool], np.ndarray] = {}

    def means(self, key: tuple[str, ...], with_episodes: bool) -> np.ndarray:
        if (key, with_episodes) not in self._cache:
            rng = generator(self.settings.seed, self.tag, *key)
            n_boot = self.settings.n_boot
            self._cache[key, with_episodes] = _boot_means(self.cells[key], rng, n_boot, with_episodes)
        return self._cache[key, with_episodes]

    def has_episodes(self, key: tuple[str, ...]) -> bool:
        return self.cells[key].episodes is not None


def prob_greater(a: Bootstrap, ka: tuple[str, ...], b: Bootstrap, kb: tuple[str, ...]) -> tuple[float, str]:
    """P(mean_a* > mean_b*) over paired-by-index independent replicates, and the comparison's basis."""
    episodes = a.has_episodes(ka) and b.has_episodes(kb)
    p = float(np.mean(a.means(ka, episodes) > b.means(kb, episodes)))
    return p, _basis(len(a.cells[ka].values), len(b.cells[kb].values), episodes)


def tau_b(x: Sequence[float], y: Sequence[float]) -> float | None:
    """Kendall's tau-b (ties corrected): sum sign(dx)sign(dy) / sqrt(#pairs untied in x * #pairs untied in y).

    None when fewer than two items or when either side is all ties (the statistic is undefined).
    """
    x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    i, j = np.triu_indices(len(x), 1)
    sx, sy = np.sign(x[i] - x[j]), np.sign(y[i] - y[j])
    denom = math.sqrt(float(np.count_nonzero(sx)) * float(np.count_nonzero(sy)))
    return float((sx * sy).sum() / denom) if denom else None
