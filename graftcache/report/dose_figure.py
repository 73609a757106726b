"""The dose-response figure: offline MSE and closed-loop progress against the dose, one row of two panels per curve
(backbone, suite, encoder), each dose's mean with its 95% interval (graftcache.analysis.dose).

The two panels share the dose axis (0: the encoder, 1: the blind zero-image policy) so that a step that moves one
curve and not the other is seen at its dose; each value axis is fitted to its data, not started at 0, because what
the figure asks is whether adjacent doses are told apart. Steps the closed loop confirms are drawn solid in the
right panel, the others dashed: the finest solid step's offline gap is the resolution in the title.
"""

from __future__ import annotations

import polars as pl
from matplotlib.figure import Figure

from graftcache import analysis as A
from graftcache.report.canvas import new_figure, value_limits

DOSE_CAPTION = (
    "Dose response: the encoder's features degraded by noise-A (0: the plain graft, 1: the zero-image control). "
    "Left: offline eval_mse, mean over seeds with a 95% t interval; right: closest approach to the target (m, lower "
    "is better), mean over the episodes of every seed with a 95% t interval. Solid steps on the right are confirmed "
    "by the paired closed-loop difference (fit seed, episode key); the title gives the resolution."
)


def _panel(ax, points: pl.DataFrame, side: str, label: str, confirmed: dict[tuple[float, float], bool] | None) -> None:
    ax.set_xlim(-0.05, 1.05)  # the whole dose range, whichever doses were measured
    have = points.drop_nulls(f"{side}_mean")
    if not len(have):
        ax.text(0.5, 0.5, "not measured", transform=ax.transAxes, ha="center", va="center", color="0.4")
        ax.set_xlabel("dose A")
        return
    x, y = have["dose"].to_list(), have[f"{side}_mean"].to_list()
    lo = [m if v is None else v for v, m in zip(have[f"{side}_lo"], y, strict=True)]
    hi = [m if v is None else v for v, m in zip(have[f"{side}_hi"], y, strict=True)]
    ax.errorbar(x, y, yerr=[[m - a for m, a in zip(y, lo, strict=True)], [b - m for m, b in zip(y, hi, strict=True)]],
                fmt="o", color="#1f77b4", capsize=3, ms=5)
    for i in range(len(x) - 1):
        solid = confirmed is None or confirmed.get((x[i], x[i + 1]), False)
        ax.plot(x[i:i + 2], y[i:i + 2], "-" if solid else "--", color="#1f77b4", lw=1.2)
    ax.set_ylim(*value_limits([*lo, *hi]))
    ax.set_xlabel("dose A")
    ax.set_ylabel(label, fontsize=8)


def figure_dose(a: A.Analysis) -> Figure | None:
    """The figure, or None without dose curves."""
    if a.dose is None:
        return None
    curves = a.dose.curves.rows(named=True)
    fig = new_figure(8.0, 2.6 * len(curves))
    axes = fig.subplots(len(curves), 2, squeeze=False)
    for (left, right), curve in zip(axes, curves, strict=True):
        ident = [pl.col(k) == curve[k] for k in ("backbone", "suite", "encoder")]
        points = a.dose.points.filter(*ident).sort("dose")
        steps = a.dose.steps.filter(*ident).sort("dose_from")
        confirmed = {(s["dose_from"], s["dose_to"]): s["confirmed"] for s in steps.iter_rows(named=True)}
        _panel(left, points, "offline", "offline eval_mse", None)
        _panel(right, points, "loop", "closest approach (m)", confirmed)
        name = f"{A.backbone_label(curve['backbone'])} / {curve['suite']} / {curve['encoder']}"
        left.set_title(f"{name}\noffline: {curve['offline_monotone'] or '—'}", fontsize=8)
        res = "—" if curve["resolution"] is None else f"{curve['resolution']:.3g}"
        right.set_title(f"closed loop: {curve['loop_monotone'] or '—'}; resolution {res}", fontsize=8)
    return fig
