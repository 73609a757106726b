"""Offline scores against closed-loop behaviour: does a lower offline score go with a better closed loop?

A *cell* here is one policy with rollouts (graftcache.analysis.policies: results rows that hold one policy, such
as a zero-image control under three encoders, are one cell, their episodes pooled and each episode key once): its
success rate over its episodes, with a 95% Wilson score interval, and the mean of each graded measure of progress
over its episodes that record it (graftcache.analysis.rollouts.GRADED_MEASURES; `grasped` as a rate).

Per (backbone, suite), offline score (CLOSED_LOOP_SCORES) and closed-loop measure (MEASURES), two agreements
(CELLS_OF), each answering its own question:
- "candidates", the plain grafts (control "none"): does the offline score order the encoders as the closed loop
  does? This is the question a user brings, and the one the report leads with;
- "with controls", every distinct policy: does looking help? Blind and native controls sit far from the grafts on
  both axes, so this figure is mostly their distance, which nobody doubts.
Each gives Spearman's rho, Kendall's tau-b and SIMPLER's mean maximum rank violation (MMRV; Li et al. 2024, arXiv
2405.05941) over the cells, with an interval from the bootstrap over cells and their episodes
(graftcache.analysis.closed_loop_boot), an interval that holds its figure.

Agreement is computed over policies, not over seed means: a policy is one trained projector, the very policy that
was scored offline and rolled out, so its score and its closed-loop value are one paired measurement. Averaging
seeds first would pair a mean score with a mean success and hide the seed noise an offline score must see through.

Signs: every measure is oriented so that higher is better (HIGHER_IS_BETTER: distances are negated) and the proxy
is -score (lower is better), so rho and tau-b are positive where lower scores go with a better closed loop, for
every measure alike; MMRV, an error in the measure's own units (a rate, metres, a fraction), is 0 where no pair is
ordered against it. They are undefined (null, and a `note` says why) with fewer than 2 cells, where every cell has
the same value of the measure (e.g. success 0 everywhere: there is no order to agree with) and where no episode
records a graded measure (format-1 rollouts); rho and tau-b also where every cell has the same score. A
non-finite or null score leaves its cell out of that score's agreement, a null measure out of that measure's.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from statistics import NormalDist

import numpy as np
import polars as pl

from graftcache.analysis.closed_loop_boot import (
    N_BOOT,
    mmrv_rows,
    spearman_rows,
    symmetric_interval,
    tau_b_rows,
    two_level,
)
from graftcache.analysis.looks import FIXED_LEVEL, Looks
from graftcache.analysis.paired_control import paired_control
from graftcache.analysis.pairwise import pairwise
from graftcache.analysis.policies import POLICY, policies, policy_episodes
from graftcache.analysis.rollouts import GRADED_MEASURES, HIGHER_IS_BETTER, MEASURES
from graftcache.analysis.stats import generator, tau_b
from graftcache.analysis.table import GROUP, PLAIN

#: The offline scores set against the closed loop, each a results column (lower is better)
CLOSED_LOOP_SCORES = ("eval_mse", "eval_ci_mse", "eval_mse_arm", "eval_mse_gripper")
#: The two-sided 95% normal quantile of the Wilson interval
Z95 = NormalDist().inv_cdf(0.975)
#: Each measure's per-cell column: a rate for the true/false ones, a mean for the others
MEASURE_COLUMNS = {m: {"success": "success_rate", "grasped": "grasped_rate"}.get(m, m) for m in MEASURES}
#: Below this share of defined replicates an interval's note says over how many it was taken (the count is always
#: in `replicates`): an interval over a minority of replicates describes only the draws where the cells differ
FEW_REPLICATES = 0.95
#: The two sets of cells each agreement is taken over: the plain grafts, and every distinct policy
CANDIDATES, WITH_CONTROLS = "candidates", "with controls"
CELLS_OF = (CANDIDATES, WITH_CONTROLS)
#: The figures of each agreement row, each with its interval columns `<name>_low` and `<name>_high`
STATISTICS = ("spearman", "kendall_tau_b", "mmrv")

CELL_SCHEMA = {
    "backbone": pl.String, "suite": pl.String, "encoder": pl.String, "control": pl.String, "seed": pl.Int64,
    "run_id": pl.String, POLICY: pl.String, "runs": pl.Int64, "episodes": pl.Int64, "successes": pl.Int64,
    "success_rate": pl.Float64, "ci_low": pl.Float64, "ci_high": pl.Float64, "graded_episodes": pl.Int64,
    **{MEASURE_COLUMNS[m]: pl.Float64 for m in GRADED_MEASURES}, **dict.fromkeys(CLOSED_LOOP_SCORES, pl.Float64),
}
AGREEMENT_SCHEMA = {
    "backbone": pl.String, "suite": pl.String, "cells_of": pl.String, "score": pl.String, "measure": pl.String,
    "cells": pl.Int64,
    **{f"{s}{part}": pl.Float64 for s in STATISTICS for part in ("", "_low", "_high")},
    "replicates": pl.Int64, "note": pl.String,
}


@dataclass(frozen=True)
class ClosedLoop:
    """What the report shows of rollouts: one row per cell (CELL_SCHEMA), one per (backbone, suite, cells_of,
    score, measure) (AGREEMENT_SCHEMA), one per (backbone, suite, measure) of the native tower against zero-image
    on the same episodes (graftcache.analysis.paired_control.CONTROL_SCHEMA), one per (backbone, suite, measure,
    pair of candidate encoders) (graftcache.analysis.pairwise.PAIRWISE_SCHEMA), and the episodes themselves, each
    policy's once (graftcache.analysis.policies.policy_episodes)."""

    cells: pl.DataFrame
    agreement: pl.DataFrame
    control: pl.DataFrame
    pairwise: pl.DataFrame
    rollouts: pl.DataFrame
    looks: Looks | None = None  # a sequential rollout's record: the closed-loop pairwise intervals are at its level

    @property
    def ungraded(self) -> int:
        """Episodes that record no graded measure (format-1 rows, or a table without the columns)."""
        return int(self.rollouts.select(pl.all_horizontal(pl.col(GRADED_MEASURES).is_null()).sum()).item())

    @property
    def kernels(self) -> dict[str | None, int]:
        """Episodes per set of kernels their policy computed on (None: not recorded), most first."""
        counts = self.rollouts.group_by("kernels").len().sort(["len", "kernels"], descending=[True, False])
        return dict(counts.iter_rows())


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
    closed-loop values (higher is better): each cell's worst ordering error, weighted by what it misjudges,
    averaged."""
    s, r = -np.asarray(score, dtype=np.float64), np.asarray(success, dtype=np.float64)
    violated = (s[:, None] < s[None, :]) != (r[:, None] < r[None, :])
    return float((np.abs(r[:, None] - r[None, :]) * violated).max(axis=1).mean())


def rollout_cells(results: pl.DataFrame, episodes: pl.DataFrame) -> pl.DataFrame:
    """Per policy with episodes (graftcache.analysis.policies: its first row by run_id, `runs` its rows), its
    success rate and Wilson interval, and each graded measure's mean over its episodes that record it, beside its
    offline scores, in (backbone, suite, encoder, control, seed) order. `episodes` is policy_episodes' table."""
    per_policy = episodes.group_by(POLICY).agg(
        episodes=pl.len(), successes=pl.col("success").sum(),
        graded_episodes=(~pl.all_horizontal(pl.col(GRADED_MEASURES).is_null())).sum(),
        **{MEASURE_COLUMNS[m]: pl.col(m).cast(pl.Float64).mean() for m in GRADED_MEASURES},
    )
    cells = policies(results).join(per_policy, on=POLICY, how="inner").sort(
        "backbone", "suite", "encoder", "control", "seed")
    bounds = [wilson(k, n) for k, n in cells.select("successes", "episodes").iter_rows()]
    return cells.with_columns(
        success_rate=pl.col("successes") / pl.col("episodes"),
        ci_low=pl.Series([lo for lo, _ in bounds], dtype=pl.Float64),
        ci_high=pl.Series([hi for _, hi in bounds], dtype=pl.Float64),
    ).select([pl.col(c).cast(t) for c, t in CELL_SCHEMA.items()])


def _episode_values(episodes: pl.DataFrame, measure: str) -> dict[str, np.ndarray]:
    """policy -> the measure over that cell's episodes that record it (true/false as 1/0), sorted: a replicate
    depends on the values, never on the order of the file's rows."""
    frame = episodes.select(POLICY, pl.col(measure).cast(pl.Float64)).drop_nulls()
    return {policy: np.sort(group[measure].to_numpy()) for (policy,), group in frame.group_by(POLICY)}


def _level(measure: str, value: float) -> str:
    """One cell's value of a measure, as the note on a tie says it."""
    if measure == "success":
        return f"success rate is {value:.0%}"
    return f"grasped rate is {value:.0%}" if measure == "grasped" else f"{measure} is {value:.4g}"


def _why_undefined(chosen: int, score: str, measure: str, recorded: int, scores: np.ndarray,
                   values: np.ndarray) -> str | None:
    """Why no agreement figure can be given over these cells (`chosen` of them, `recorded` with the measure), or
    None."""
    if not chosen:
        return "no plain graft with rollouts"
    if not recorded:
        return (f"graded measures unavailable: no rollout of these cells records {measure} (format-1 rows, or a "
                "table without it)")
    if len(scores) == 0:
        return f"no cell with rollouts has a finite {score}"
    if len(scores) == 1:
        return "1 cell: agreement needs 2 or more"
    if np.ptp(values) == 0:
        return f"every cell's {_level(measure, values[0])}: no order to agree with"
    return None


def _agree(scores: np.ndarray, good: np.ndarray, picks: np.ndarray, means: np.ndarray) -> dict[str, float | None]:
    """rho, tau-b and MMRV of -scores against `good` (higher is better), each with its symmetric interval
    (closed_loop_boot) over the two-level replicates (`picks`, the drawn cells; `means`, their oriented means) in
    which the drawn cells do not all tie (a tie everywhere has no order, as for the point figure)."""
    rho, tau, worst = spearman(-scores, good), tau_b(-scores, good), mmrv(scores, good)
    kept = np.ptp(means, axis=1) > 0
    drawn, means = scores[picks[kept]], means[kept]
    out: dict[str, float | None] = {"replicates": int(kept.sum())}
    for name, point, draws, bounds in (("spearman", rho, spearman_rows, (-1.0, 1.0)),
                                       ("kendall_tau_b", tau, tau_b_rows, (-1.0, 1.0)),
                                       ("mmrv", worst, None, (0.0, math.inf))):
        if point is None:
            out |= {name: None, f"{name}_low": None, f"{name}_high": None}
            continue
        replicates = mmrv_rows(drawn, means) if draws is None else draws(-drawn, means)
        out[name], (out[f"{name}_low"], out[f"{name}_high"]) = point, symmetric_interval(point, replicates, *bounds)
    return out


def _which(group: pl.DataFrame) -> dict[str, pl.DataFrame]:
    """The two sets of cells each agreement is taken over (CELLS_OF)."""
    return {CANDIDATES: group.filter(pl.col("control") == PLAIN), WITH_CONTROLS: group}


def agreement(cells: pl.DataFrame, episodes: pl.DataFrame, *, seed: int = 0) -> pl.DataFrame:
    """Per (backbone, suite), CELLS_OF set of cells, MEASURES measure and CLOSED_LOOP_SCORES score: how many cells
    (policies) have both, and rho, tau-b (both of -score against the measure oriented better-is-higher) and MMRV
    over them, each with its interval from the bootstrap over cells and their episodes (closed_loop_boot: N_BOOT
    replicates, generators seeded by `seed` and what is resampled); null where undefined (see the module
    docstring), `note` saying why. `episodes` is policy_episodes' table."""
    records = []
    empty = dict.fromkeys(c for c in AGREEMENT_SCHEMA if c not in ("backbone", "suite", "cells_of", "score",
                                                                   "measure", "cells", "note"))
    values = {m: _episode_values(episodes, m) for m in MEASURES}
    for (backbone, suite), group in cells.group_by(GROUP, maintain_order=True):
        for cells_of, chosen in _which(group.sort(POLICY)).items():
            for measure in MEASURES:
                sign, column = (1.0 if HIGHER_IS_BETTER[measure] else -1.0), MEASURE_COLUMNS[measure]
                have = chosen.filter(pl.col(column).is_not_null())
                for score in CLOSED_LOOP_SCORES:
                    valid = have.filter(pl.col(score).is_finite())
                    scores, means = valid[score].to_numpy(), valid[column].to_numpy()
                    note = _why_undefined(len(chosen), score, measure, len(have), scores, means)
                    figures = empty
                    if not note:
                        rng = generator(seed, "closed-loop", backbone, suite, cells_of, score, measure)
                        picks, drawn = two_level([values[measure][p] for p in valid[POLICY]], rng)
                        figures = _agree(scores, sign * means, picks, sign * drawn)
                    if not note and figures["spearman"] is None:
                        note = f"every cell has the same {score}: rho and tau-b undefined"
                    if not note and figures["replicates"] < FEW_REPLICATES * N_BOOT:
                        note = (f"intervals over only {figures['replicates']} of {N_BOOT} replicates (in the others "
                                f"every drawn cell had one {measure}: no order)")
                    records.append({"backbone": backbone, "suite": suite, "cells_of": cells_of, "score": score,
                                    "measure": measure, "cells": len(scores), **figures, "note": note})
    return pl.DataFrame(records, schema=AGREEMENT_SCHEMA)


def closed_loop(results: pl.DataFrame, rollouts: pl.DataFrame, *, seed: int = 0,
                looks: Looks | None = None) -> ClosedLoop:
    """Cells (one per policy), both agreements, the paired control and the pairwise verdicts of every measure
    from a conformed results table (every SCHEMA column, scores unreplaced) and rollouts
    (graftcache.analysis.rollouts.read_rollouts); `seed` seeds every bootstrap. `looks`: the record of the
    sequential rollout that wrote them (graftcache.analysis.looks), whose level the pairwise closed-loop intervals
    take; None: 95%."""
    episodes = policy_episodes(results, rollouts)
    cells = rollout_cells(results, episodes)
    level = FIXED_LEVEL if looks is None else looks.level
    verdicts = pl.concat([pairwise(results, rollouts, measure=m, closed_level=level, seed=seed) for m in MEASURES])
    return ClosedLoop(cells, agreement(cells, episodes, seed=seed), paired_control(cells, episodes, seed=seed),
                      verdicts, episodes, looks)
