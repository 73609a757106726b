"""The dose-response calibration: what offline MSE resolves, measured against the closed loop on one encoder whose
features are degraded in known steps (the `noise-A` controls, graftcache/fit/dose.py).

Per (backbone, suite, encoder) with dose cells, the curve runs from dose 0 (the encoder's plain cells) through every
`noise-A` level to dose 1 (the zero-image cells: the blind policy; they ignore the encoder, so a (backbone, suite,
seed)'s zero-image cell of any encoder stands in where the encoder's own is missing). At each dose:

- offline: eval_mse, mean over the fit seeds with a 95% t interval over them;
- closed loop: the closest approach to the target (`min_target_distance_m`), mean over every episode of the dose's
  cells (the seeds pooled) with a 95% t interval over those episodes.

Between adjacent doses (a step), both differences are paired, higher dose minus lower: offline by fit seed (the same
held-out frames), closed loop by (fit seed, episode key PAIR_KEY: the same scene, init state and perturbation), each
with a 95% t interval over its pairs. A step is *resolved* by a side when its interval excludes 0; the closed loop
*confirms* a step when it is resolved in the direction the offline difference has (both worse, or both better).

A curve is `monotone` when every step's mean moves towards blindness (eval_mse and distance rise with the dose),
`monotone within noise` when every step against it is unresolved, else `not monotone`. The RESOLUTION is the
smallest |offline eval_mse difference| among the steps the closed loop confirms at the episodes spent: the finest
offline gap the closed loop has been shown to see; null, with a note, when it confirms none.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import polars as pl
from scipy import stats

from graftcache.analysis.rollouts import PAIR_KEY
from graftcache.analysis.table import PLAIN, ZERO_IMAGE
from graftcache.requests import DOSE_PREFIX

MEASURE = "min_target_distance_m"   # the graded measure the curve draws (metres, lower is better)
CONFIDENCE = 0.95
CURVE = ["backbone", "suite", "encoder"]

POINT_SCHEMA = {
    "backbone": pl.String, "suite": pl.String, "encoder": pl.String, "dose": pl.Float64, "control": pl.String,
    "offline_mean": pl.Float64, "offline_lo": pl.Float64, "offline_hi": pl.Float64, "seeds": pl.Int64,
    "loop_mean": pl.Float64, "loop_lo": pl.Float64, "loop_hi": pl.Float64, "episodes": pl.Int64,
}
STEP_SCHEMA = {
    "backbone": pl.String, "suite": pl.String, "encoder": pl.String, "dose_from": pl.Float64, "dose_to": pl.Float64,
    "offline_diff": pl.Float64, "offline_lo": pl.Float64, "offline_hi": pl.Float64, "offline_pairs": pl.Int64,
    "loop_diff": pl.Float64, "loop_lo": pl.Float64, "loop_hi": pl.Float64, "loop_pairs": pl.Int64,
    "confirmed": pl.Boolean,
}
CURVE_SCHEMA = {
    "backbone": pl.String, "suite": pl.String, "encoder": pl.String, "doses": pl.Int64,
    "offline_monotone": pl.String, "loop_monotone": pl.String, "resolution": pl.Float64, "note": pl.String,
}


@dataclass(frozen=True)
class DoseCurves:
    points: pl.DataFrame   # POINT_SCHEMA: one row per (curve, dose)
    steps: pl.DataFrame    # STEP_SCHEMA: one row per (curve, adjacent doses)
    curves: pl.DataFrame   # CURVE_SCHEMA: one row per curve


def dose_of(control: str) -> float | None:
    """The dose a control's cells stand at: 0 plain, A for noise-A, 1 zero-image, None for any other control."""
    if control == PLAIN:
        return 0.0
    if control == ZERO_IMAGE:
        return 1.0
    if control.startswith(DOSE_PREFIX):
        try:
            return float(control.removeprefix(DOSE_PREFIX))
        except ValueError:
            return None
    return None


def t_interval(values: np.ndarray) -> tuple[float | None, float | None, float | None]:
    """(mean, lo, hi) of `values` with a CONFIDENCE t interval; the interval is null below 2 values, the mean too
    with none."""
    values = np.asarray(values, dtype=float)
    if not len(values):
        return None, None, None
    mean = float(values.mean())
    if len(values) < 2:
        return mean, None, None
    half = float(stats.t.ppf(0.5 + CONFIDENCE / 2, len(values) - 1) * values.std(ddof=1) / math.sqrt(len(values)))
    return mean, mean - half, mean + half


def _cells(results: pl.DataFrame, rolled: set[str]) -> pl.DataFrame:
    """The finite rows at a dose, with it, for every encoder that has noise-A rows. Its dose-1 cell of a seed is a
    zero-image row of that (backbone, suite, seed): one that was rolled out (`rolled`: run_ids with episodes) first,
    then its own encoder's, then the first by run_id."""
    rows = results.filter(pl.col("eval_mse").is_finite()).with_columns(
        dose=pl.col("control").map_elements(dose_of, return_dtype=pl.Float64)).drop_nulls("dose")
    dosed = rows.filter(pl.col("control").str.starts_with(DOSE_PREFIX)).select(CURVE).unique()
    own = rows.join(dosed, on=CURVE).filter(pl.col("dose") < 1)
    blind = dosed.join(rows.filter(pl.col("dose") == 1).rename({"encoder": "blind_encoder"}), on=["backbone", "suite"])
    blind = (blind.with_columns(rolled=pl.col("run_id").is_in(list(rolled)),
                                own=pl.col("blind_encoder") == pl.col("encoder"))
             .sort([*CURVE, "seed", "rolled", "own", "run_id"], descending=[False] * 4 + [True, True, False])
             .unique([*CURVE, "seed"], keep="first", maintain_order=True))
    return pl.concat([own, blind.select(own.columns)], how="vertical_relaxed")


def _episodes(cells: pl.DataFrame, rollouts: pl.DataFrame | None) -> pl.DataFrame:
    """Every graded episode of the cells: their curve, dose and seed, the pair key, the measure."""
    key = list(PAIR_KEY)
    if rollouts is None:
        return pl.DataFrame(schema={**{c: pl.String for c in CURVE}, "dose": pl.Float64, "seed": pl.Int64,
                                    **{f"ep_{k}": t for k, t in PAIR_KEY.items()}, MEASURE: pl.Float64})
    got = rollouts.drop_nulls(MEASURE).select("run_id", MEASURE, *[pl.col(k).alias(f"ep_{k}") for k in key])
    return cells.select([*CURVE, "dose", "seed", "run_id"]).join(got, on="run_id").drop("run_id")


def _paired(a: pl.DataFrame, b: pl.DataFrame, on: list[str], value: str) -> tuple[np.ndarray, int]:
    """b - a per key of `on` both hold (each side's mean where a key repeats)."""
    mean_a = a.group_by(on).agg(pl.col(value).mean())
    mean_b = b.group_by(on).agg(pl.col(value).mean())
    both = mean_a.join(mean_b, on=on, suffix="_b")
    return (both[f"{value}_b"] - both[value]).to_numpy(), len(both)


def _monotone(diffs: list[tuple[float | None, float | None, float | None]]) -> str | None:
    """How a curve's steps move with the dose (each step: mean difference, interval): see the module docstring."""
    known = [d for d in diffs if d[0] is not None]
    if not known:
        return None
    against = [d for d in known if d[0] < 0]
    if not against:
        return "monotone"
    resolved = [d for d in against if d[2] is not None and d[2] < 0]
    return "not monotone" if resolved else "monotone within noise"


def dose_curves(results: pl.DataFrame, rollouts: pl.DataFrame | None = None) -> DoseCurves | None:
    """The dose curves of `results` (conformed), with `rollouts` (read_rollouts) where given; None when the table has
    no noise-A rows."""
    cells = _cells(results, set() if rollouts is None else set(rollouts.drop_nulls(MEASURE)["run_id"].to_list()))
    if not len(cells):
        return None
    episodes = _episodes(cells, rollouts)
    pair_on = ["seed", *[f"ep_{k}" for k in PAIR_KEY]]
    points, steps, curves = [], [], []
    for (backbone, suite, encoder), curve in cells.sort(CURVE).group_by(CURVE, maintain_order=True):
        ident = {"backbone": backbone, "suite": suite, "encoder": encoder}
        eps = episodes.filter(pl.col("backbone") == backbone, pl.col("suite") == suite, pl.col("encoder") == encoder)
        doses = sorted(set(curve["dose"].to_list()))
        for dose in doses:
            at = curve.filter(pl.col("dose") == dose)
            loop = eps.filter(pl.col("dose") == dose)[MEASURE].to_numpy()
            om, olo, ohi = t_interval(at["eval_mse"].to_numpy())
            lm, llo, lhi = t_interval(loop)
            points.append({**ident, "dose": dose, "control": at["control"][0], "offline_mean": om, "offline_lo": olo,
                           "offline_hi": ohi, "seeds": len(at), "loop_mean": lm, "loop_lo": llo, "loop_hi": lhi,
                           "episodes": len(loop)})
        offline_steps, loop_steps, confirmed = [], [], []
        for lo, hi in zip(doses, doses[1:], strict=False):
            off, n_off = _paired(curve.filter(pl.col("dose") == lo), curve.filter(pl.col("dose") == hi), ["seed"],
                                 "eval_mse")
            lp, n_lp = _paired(eps.filter(pl.col("dose") == lo), eps.filter(pl.col("dose") == hi), pair_on, MEASURE)
            o, lp_ = t_interval(off), t_interval(lp)
            yes = (o[0] is not None and lp_[1] is not None and o[0] != 0
                   and (lp_[1] > 0 if o[0] > 0 else lp_[2] < 0))
            steps.append({**ident, "dose_from": lo, "dose_to": hi, "offline_diff": o[0], "offline_lo": o[1],
                          "offline_hi": o[2], "offline_pairs": n_off, "loop_diff": lp_[0], "loop_lo": lp_[1],
                          "loop_hi": lp_[2], "loop_pairs": n_lp, "confirmed": yes})
            offline_steps.append(o)
            loop_steps.append(lp_)
            if yes:
                confirmed.append(abs(o[0]))
        spent = len(eps)
        note = None if confirmed else (
            f"no step confirmed by the closed loop at the {spent} episodes spent" if spent
            else "no graded episodes: the closed loop was not measured")
        curves.append({**ident, "doses": len(doses), "offline_monotone": _monotone(offline_steps),
                       "loop_monotone": _monotone(loop_steps), "resolution": min(confirmed) if confirmed else None,
                       "note": note})
    return DoseCurves(pl.DataFrame(points, schema=POINT_SCHEMA), pl.DataFrame(steps, schema=STEP_SCHEMA),
                      pl.DataFrame(curves, schema=CURVE_SCHEMA))
