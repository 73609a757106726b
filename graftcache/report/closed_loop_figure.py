"""The validity figure: each rolled-out cell's offline score against its closed-loop progress and success.

One row of panels per (backbone, suite), two panels each: the closest approach of the end effector to the target
(`min_target_distance_m`, the graded measure a reach -> grasp -> lift policy moves first) and the success rate,
both against the report's offline score. Each cell (one run_id: one seed) is a dot, so the seed spread is seen,
not averaged away; the controls are marked apart from the plain grafts (native tower, native-graft, zero-image),
because the figure's first question is whether the policies that read the images (native, grafts) reach closer
than the one that cannot (zero-image). The distance axis is inverted so that up is better in both panels, and
every value axis is fitted to its data rather than started at 0.
"""

from __future__ import annotations

import polars as pl
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from matplotlib.lines import Line2D

from graftcache import analysis as A
from graftcache.report.canvas import new_figure, value_limits

#: The measures drawn against the offline score, left to right, with their axis labels
PANELS = {"min_target_distance_m": "closest approach to the target (m; up is closer)",
          "success": "success rate (95% Wilson)"}
#: control -> (marker, colour, size, label); plain grafts are circles in their encoder's colour
CONTROL_MARKS = {
    A.NATIVE_CONTROL: ("*", "#000000", 12, "native tower"),
    A.NATIVE_GRAFT_CONTROL: ("D", "#8c564b", 6, "native-graft (tower through the wrapper)"),
    A.ZERO_IMAGE: ("X", "#7f7f7f", 8, "zero-image (no images)"),
}
OTHER_CONTROL_MARKER = "^"
CLOSED_LOOP_CAPTION = (
    "Offline score against closed-loop progress, one dot per cell (run_id: one seed); controls marked apart. Left: "
    "the closest approach of the end effector to the target (axis inverted, up is better); right: the success rate "
    "with its 95% Wilson interval. Titles: Spearman ρ, Kendall τb and MMRV with their 95% bootstrap intervals over "
    "episodes (positive ρ, τb: lower scores go with a better closed loop); the left panels also give the native "
    "tower's paired difference from zero-image on the same episodes."
)


def _interval(row: dict, name: str, fmt: str) -> str:
    low, high = row[f"{name}_low"], row[f"{name}_high"]
    span = "" if low is None else f" [{low:{fmt}}, {high:{fmt}}]"
    return "—" if row[name] is None else f"{row[name]:{fmt}}{span}"


def agreement_title(row: dict | None) -> str:
    """A panel's agreement figures with their intervals, or why there are none."""
    if row is None:
        return ""
    if row["mmrv"] is None:
        return f"undefined: {row['note']}"
    return (f"ρ {_interval(row, 'spearman', '+.2f')} · τb {_interval(row, 'kendall_tau_b', '+.2f')}\n"
            f"MMRV {_interval(row, 'mmrv', '.3g')}")


def control_line(row: dict | None) -> str:
    """The native tower minus zero-image on the same episodes, as a panel prints it."""
    if row is None or row["difference"] is None:
        return "" if row is None else f"native − zero-image: {row['note']}"
    unit = " m" if row["measure"].endswith("_m") else ""
    span = "" if row["ci_low"] is None else f" [{row['ci_low']:+.3g}, {row['ci_high']:+.3g}]"
    return f"native − zero-image: {row['difference']:+.3g}{unit}{span} over {row['pairs']} paired episodes"


def _mark(r: dict, colors: dict[str, str]) -> dict:
    """A cell's marker: its control's, or for grafts (plain circles, other controls triangles) its encoder's
    colour."""
    if r["control"] in CONTROL_MARKS:
        marker, color, size, _ = CONTROL_MARKS[r["control"]]
        return {"marker": marker, "color": color, "ms": size}
    return {"marker": "o" if r["control"] == A.PLAIN else OTHER_CONTROL_MARKER, "color": colors[r["encoder"]], "ms": 6}


def _panel(ax: Axes, cells: pl.DataFrame, score: str, measure: str, colors: dict[str, str]) -> None:
    """One panel: every cell with a finite score and the measure, at (score, measure)."""
    column = A.MEASURE_COLUMNS[measure]
    drawn = cells.filter(pl.col(score).is_finite(), pl.col(column).is_not_null())
    for r in drawn.iter_rows(named=True):
        spread = None
        if measure == "success":
            spread = [[r["success_rate"] - r["ci_low"]], [r["ci_high"] - r["success_rate"]]]
        ax.errorbar(r[score], r[column], yerr=spread, ls="", capsize=3, lw=1.1, alpha=0.8, zorder=3,
                    markeredgewidth=0.5, markeredgecolor="white", **_mark(r, colors))
    if not len(drawn):
        missing = "graded measures unavailable\n(format-1 rollouts)" if measure != "success" else f"no cell has {score}"
        ax.text(0.5, 0.5, missing, transform=ax.transAxes, ha="center", va="center", color="0.4", fontsize=8)
    elif measure == "success":
        ax.set_xlim(*value_limits(drawn[score].to_list()))
        ax.set_ylim(-0.05, 1.05)
    else:
        ax.set_xlim(*value_limits(drawn[score].to_list()))
        low, high = value_limits(drawn[column].to_list())
        ax.set_ylim(high, low)  # inverted: a smaller distance is better, and up is better in every panel
    ax.grid(color="0.9", zorder=0)
    ax.set_xlabel(f"{score} (lower is better; axis not from 0)", fontsize=8)
    ax.set_ylabel(PANELS[measure], fontsize=8)
    ax.tick_params(labelsize=7)


def figure_closed_loop(a: A.Analysis) -> Figure | None:
    """Per (backbone, suite) with rollouts: the closest approach and the success rate against the report's
    `--score`, one dot per cell, controls marked; titles give the agreement with its intervals and the paired
    control line. None without rollouts."""
    if a.closed_loop is None or not len(a.closed_loop.cells):
        return None
    loop, score = a.closed_loop, A.SCORES[a.score][0]
    groups = loop.cells.select(A.GROUP).unique(maintain_order=True).rows()
    fig = new_figure(4.2 * len(PANELS), 3.4 * len(groups) + 0.9)
    axes = fig.subplots(len(groups), len(PANELS), squeeze=False)
    encoders = sorted(set(loop.cells.filter(~pl.col("control").is_in(list(CONTROL_MARKS)))["encoder"]))
    colors = {e: f"C{i % 10}" for i, e in enumerate(encoders)}
    agree = {(r["backbone"], r["suite"], r["measure"]): r
             for r in loop.agreement.filter(pl.col("score") == score).iter_rows(named=True)}
    control = {(r["backbone"], r["suite"], r["measure"]): r for r in loop.control.iter_rows(named=True)}
    for row, (backbone, suite) in zip(axes, groups):
        cells = loop.cells.filter(pl.col("backbone") == backbone, pl.col("suite") == suite)
        for ax, measure in zip(row, PANELS):
            _panel(ax, cells, score, measure, colors)
            key = (backbone, suite, measure)
            ax.set_title(f"{A.backbone_label(backbone)} · {suite}\n{agreement_title(agree.get(key))}", fontsize=8)
            if measure != "success" and (line := control_line(control.get(key))):
                ax.text(0.02, 0.02, line, transform=ax.transAxes, fontsize=6.5, color="0.25", va="bottom")
    present = set(loop.cells["control"])
    handles = [Line2D([], [], ls="", marker="o", color=colors[e], label=e) for e in encoders]
    handles += [Line2D([], [], ls="", marker=m, color=c, markersize=s * 0.8, label=label)
                for control, (m, c, s, label) in CONTROL_MARKS.items() if control in present]
    fig.legend(handles=handles, loc="outside lower center", ncols=min(len(handles), 4), fontsize=7,
               title="one dot per cell (run_id); grafts by encoder, controls by marker", title_fontsize=7)
    return fig
