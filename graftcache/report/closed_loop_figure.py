"""The validity figure: each rolled-out policy's offline score against its closed-loop progress and success.

One row of panels per (backbone, suite): the closest approach of the end effector to the target
(`min_target_distance_m`, the graded measure a reach -> grasp -> lift policy moves first) against the report's
offline score over every policy with the controls; the same zoomed to the candidates (the plain grafts), whose
cluster the controls would otherwise squeeze into a corner, though it holds the question a user brings (which
encoder?); and the success rate. Each cell (one policy: one seed) is a dot, so the seed spread is seen, not averaged
away; the controls are marked apart from the plain grafts (native tower, native-graft, zero-image), and the
candidates' box is outlined in the wide panel. A panel whose agreement is undefined in every row (success 0
everywhere, a graded measure no episode records) is dropped: it could only say so, and the report's text does; a
row's panel of a set none of whose cells was rolled out there (no plain graft, say) is left blank but for a line
saying so. The
distance axis is inverted so that up is better in every panel, and every value axis is fitted to its data rather
than started at 0.
"""

from __future__ import annotations

import polars as pl
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Rectangle

from graftcache import analysis as A
from graftcache.report.canvas import new_figure, value_limits

#: The panels, left to right: (measure, the cells it draws and its agreement is over)
PANELS = (("min_target_distance_m", A.WITH_CONTROLS), ("min_target_distance_m", A.CANDIDATES),
          ("success", A.WITH_CONTROLS))
#: Each measure's axis label
LABELS = {"min_target_distance_m": "closest approach to the target (m; up is closer)",
          "success": "success rate (95% Wilson)"}
#: control -> (marker, colour, size, label); plain grafts are circles in their encoder's colour
CONTROL_MARKS = {
    A.NATIVE_CONTROL: ("*", "#000000", 12, "native tower"),
    A.NATIVE_GRAFT_CONTROL: ("D", "#8c564b", 6, "native-graft (tower through the wrapper)"),
    A.ZERO_IMAGE: ("X", "#7f7f7f", 8, "zero-image (no images)"),
}
OTHER_CONTROL_MARKER = "^"
CLOSED_LOOP_CAPTION = (
    "Offline score against closed-loop progress, one dot per policy (one seed; a policy recorded under several rows "
    "is one dot); controls marked apart. Left: the closest approach of the end effector to the target over every "
    "policy with the controls (axis inverted, up is better; the dashed box is the middle panel's); middle: the same "
    "zoomed to the candidates (plain grafts); right, where any row's agreement is defined: the success rate with its "
    "95% Wilson interval. Titles: Spearman ρ, Kendall τb and MMRV over the panel's cells with their 95% intervals "
    "from a bootstrap over cells and their episodes (positive ρ, τb: lower scores go with a better closed loop); "
    "the left panels also give the native tower's paired difference from zero-image on the same episodes."
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
        return f"{row['cells_of']}: undefined: {row['note']}"
    return (f"{row['cells_of']} ({row['cells']}): ρ {_interval(row, 'spearman', '+.2f')} · "
            f"τb {_interval(row, 'kendall_tau_b', '+.2f')}\nMMRV {_interval(row, 'mmrv', '.3g')}")


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


def _limits(drawn: pl.DataFrame, score: str, column: str) -> tuple[tuple[float, float], tuple[float, float]]:
    """The x and (inverted) y limits fitted to the drawn cells."""
    low, high = value_limits(drawn[column].to_list())
    return value_limits(drawn[score].to_list()), (high, low)


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
        xlim, ylim = _limits(drawn, score, column)
        ax.set_xlim(*xlim)
        ax.set_ylim(*ylim)  # inverted: a smaller distance is better, and up is better in every panel
    ax.grid(color="0.9", zorder=0)
    ax.set_xlabel(f"{score} (lower is better; axis not from 0)", fontsize=8)
    ax.set_ylabel(LABELS[measure], fontsize=8)
    ax.tick_params(labelsize=7)


def _outline(ax: Axes, candidates: pl.DataFrame, score: str, column: str) -> None:
    """The candidates' panel's box, dashed, in the panel with the controls."""
    drawn = candidates.filter(pl.col(score).is_finite(), pl.col(column).is_not_null())
    if len(drawn) < 2:
        return
    (x0, x1), (y1, y0) = _limits(drawn, score, column)
    ax.add_patch(Rectangle((x0, y0), x1 - x0, y1 - y0, fill=False, ls="--", lw=0.8, ec="0.45", zorder=2))


def drawn_panels(agreement: pl.DataFrame, score: str) -> list[tuple[str, str]]:
    """PANELS whose agreement is defined in at least one (backbone, suite): the others could only say
    "undefined"."""
    defined = agreement.filter(pl.col("score") == score, pl.col("mmrv").is_not_null())
    kept = set(defined.select("measure", "cells_of").iter_rows())
    return [p for p in PANELS if p in kept]


def figure_closed_loop(a: A.Analysis) -> Figure | None:
    """Per (backbone, suite) with rollouts: the closest approach over every policy and over the candidates, and
    the success rate, against the report's `--score`, one dot per policy, controls marked; titles give the
    agreement with its intervals and the paired control line. Panels undefined in every row are dropped. None
    without rollouts, or with no panel left."""
    if a.closed_loop is None or not len(a.closed_loop.cells):
        return None
    loop, score = a.closed_loop, A.SCORES[a.score][0]
    panels = drawn_panels(loop.agreement, score)
    if not panels:
        return None
    groups = loop.cells.select(A.GROUP).unique(maintain_order=True).rows()
    fig = new_figure(4.2 * len(panels), 3.5 * len(groups) + 0.9)
    axes = fig.subplots(len(groups), len(panels), squeeze=False)
    encoders = sorted(set(loop.cells.filter(~pl.col("control").is_in(list(CONTROL_MARKS)))["encoder"]))
    colors = {e: f"C{i % 10}" for i, e in enumerate(encoders)}
    agree = {(r["backbone"], r["suite"], r["measure"], r["cells_of"]): r
             for r in loop.agreement.filter(pl.col("score") == score).iter_rows(named=True)}
    control = {(r["backbone"], r["suite"], r["measure"]): r for r in loop.control.iter_rows(named=True)}
    for row, (backbone, suite) in zip(axes, groups):
        cells = loop.cells.filter(pl.col("backbone") == backbone, pl.col("suite") == suite)
        candidates = cells.filter(pl.col("control") == A.PLAIN)
        for ax, (measure, cells_of) in zip(row, panels):
            shown = candidates if cells_of == A.CANDIDATES else cells
            if not len(shown):  # nothing of this set was rolled out here: the panel could only say so
                ax.axis("off")
                ax.text(0.5, 0.5, f"{A.backbone_label(backbone)} · {suite}\nno {cells_of} cell rolled out",
                        transform=ax.transAxes, ha="center", va="center", color="0.4", fontsize=8)
                continue
            _panel(ax, shown, score, measure, colors)
            ax.set_title(f"{A.backbone_label(backbone)} · {suite}\n"
                         f"{agreement_title(agree.get((backbone, suite, measure, cells_of)))}", fontsize=7.5)
            if measure != "success" and cells_of == A.WITH_CONTROLS:
                _outline(ax, candidates, score, A.MEASURE_COLUMNS[measure])
                if line := control_line(control.get((backbone, suite, measure))):
                    ax.text(0.02, 0.02, line, transform=ax.transAxes, fontsize=6.5, color="0.25", va="bottom")
    present = set(loop.cells["control"])
    handles = [Line2D([], [], ls="", marker="o", color=colors[e], label=e) for e in encoders]
    handles += [Line2D([], [], ls="", marker=m, color=c, markersize=s * 0.8, label=label)
                for control, (m, c, s, label) in CONTROL_MARKS.items() if control in present]
    others = sorted(present - set(CONTROL_MARKS) - {A.PLAIN})
    if others:  # noise-A doses, pool-HxW, lora: the encoder's colour, one marker
        shown = ", ".join(others[:3]) + (", ..." if len(others) > 3 else "")
        handles.append(Line2D([], [], ls="", marker=OTHER_CONTROL_MARKER, color="0.5", label=f"other controls "
                              f"({shown}), in their encoder's colour"))
    fig.legend(handles=handles, loc="outside lower center", ncols=min(len(handles), 4), fontsize=7,
               title="one dot per policy; grafts by encoder, controls by marker", title_fontsize=7)
    return fig
