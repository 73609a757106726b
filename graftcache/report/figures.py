"""The report's figures, one function each: Analysis in, matplotlib Figure (or None when there is nothing to
draw) out. They are bare Agg figures (no pyplot state), which keeps report generation headless and lets
the notebook display the very same Figure objects.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import polars as pl
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from matplotlib.lines import Line2D

from graftcache import analysis as A
from graftcache.report.canvas import grid, new_figure, value_limits
from graftcache.report.closed_loop_figure import CLOSED_LOOP_CAPTION, figure_closed_loop
from graftcache.report.document import Block, Image

TIER_COLOR, OTHER_COLOR = "#1f77b4", "#a0a0a0"
SMALL_WINNER_COLOR, LARGE_WINNER_COLOR, BOTH_WINNER_COLOR = "#d62728", "#9467bd", "#000000"
CONTROL_COLORS = {A.ZERO_IMAGE: "#444444", A.SHUFFLED_IMAGE: "#ff7f0e"}
LABEL_INCH_PER_CHAR = 0.06  # width of one 7-pt tick-label character, to size panels around encoder names


def _plain_values(a: A.Analysis, backbone: str, suite: str, encoder: str) -> list[float]:
    rows = a.results.filter(
        pl.col("control") == A.PLAIN,
        pl.col("backbone") == backbone,
        pl.col("suite") == suite,
        pl.col("encoder") == encoder,
    )
    return [v for v in rows["eval_mse"].to_list() if v is not None and np.isfinite(v)]


def figure_mse(a: A.Analysis) -> Figure | None:
    """Mean eval MSE per encoder with its min-max range over seeds, each seed as a dot, the top tier in
    colour; one panel per (backbone, suite), its MSE axis fitted to the panel's data. Missing cells are
    labelled, not skipped. None when there are no plain-graft rows."""
    panels = [(b, s) for b in a.backbones for s in a.suites]
    if not panels:
        return None
    n_enc = a.band.group_by(A.GROUP).len()["len"].max()
    fig = new_figure(4.4 * len(a.suites), (0.45 * n_enc + 1.3) * len(a.backbones))
    axes = fig.subplots(len(a.backbones), len(a.suites), squeeze=False)
    for (backbone, suite), ax in zip(panels, axes.flat):
        cells = a.band.filter(pl.col("backbone") == backbone, pl.col("suite") == suite).sort(
            "mean", "encoder", nulls_last=True
        )
        drawn: list[float] = []
        for y, r in enumerate(cells.iter_rows(named=True)):
            if r["mean"] is None:
                ax.text(0.02, y, "missing", transform=ax.get_yaxis_transform(), va="center", color="0.4",
                        fontsize=8, style="italic")
                continue
            color = TIER_COLOR if r["in_band"] else OTHER_COLOR
            spread = [[r["mean"] - r["min"]], [r["max"] - r["mean"]]]
            ax.errorbar(r["mean"], y, xerr=spread, fmt="D", color=color, ms=7, capsize=4, lw=1.6, zorder=3)
            vals = _plain_values(a, backbone, suite, r["encoder"])
            ax.scatter(vals, np.full(len(vals), y + 0.25), s=12, color="black", alpha=0.75, zorder=4,
                       linewidths=0)
            drawn += [r["mean"], *vals]
        if drawn:
            ax.set_xlim(*value_limits(drawn))
        ax.set_yticks(range(len(cells)), cells["encoder"].to_list(), fontsize=8)
        ax.set_ylim(len(cells) - 0.5, -0.5)
        ax.grid(axis="x", color="0.9", zorder=0)
        flagged = set(cells["basis"].drop_nulls()) - set(A.SOLID_BASES) - {A.BASIS_MISSING}
        ax.set_title(f"{A.backbone_label(backbone)} · {suite}" + (" (1 seed)" if flagged else ""), fontsize=9)
        ax.set_xlabel("offline action MSE (axis not from 0)", fontsize=8)
        ax.tick_params(axis="x", labelsize=7)
    fig.legend(
        handles=[
            Line2D([], [], ls="", marker="D", color=TIER_COLOR,
                   label=f"top tier mean (not separable from best, {a.boot.confidence:.0%})"),
            Line2D([], [], ls="", marker="D", color=OTHER_COLOR, label="mean outside top tier"),
            Line2D([], [], color="0.3", label="min–max over seeds"),
            Line2D([], [], ls="", marker="o", color="black", markersize=4, label="per-seed MSE"),
        ],
        loc="outside lower center",
        ncols=2 if len(a.suites) > 1 else 1,  # one panel is too narrow for two legend columns
        fontsize=8,
    )
    return fig


def _rank_ticks(ax: Axes, ranks: dict[str, int], shared: set[str], number_first: bool) -> None:
    """Encoder names as the rank axis' tick labels ("name  1" left, "1  name" right; tied names share a
    tick), so constrained layout makes room for them instead of names overprinting the numbers."""
    by_rank: dict[int, list[str]] = {}
    for enc, r in ranks.items():
        by_rank.setdefault(r, []).append(enc + ("" if enc in shared else " *"))
    ticks = sorted(by_rank)
    names = [", ".join(sorted(by_rank[r])) for r in ticks]
    labels = [f"{r}  {n}" if number_first else f"{n}  {r}" for r, n in zip(ticks, names)]
    ax.set_yticks(ticks, labels, fontsize=7)


def figure_rank_transfer(a: A.Analysis) -> Figure | None:
    """Slope chart per suite: rank on the small backbone (left) vs the large one (right), one line per
    encoder run on both; each backbone's winner is coloured, and a filled dot marks membership of that
    side's top tier, so both transfer directions can be read off. None unless the ladder has exactly two
    backbones (more: figure_rank_bump)."""
    if len(a.ladder.backbones) != 2 or not len(a.verdicts):
        return None
    rows, cols = grid(len(a.suites))
    longest = max(len(e) for e in a.band["encoder"]) + 6
    n_enc = a.band.group_by(A.GROUP).len()["len"].max()
    panel_width = max(1.8 + 2 * LABEL_INCH_PER_CHAR * longest, 3.2)  # names on both sides; room for titles
    fig = new_figure(panel_width * cols, (0.35 * n_enc + 1.9) * rows)
    axes = fig.subplots(rows, cols, squeeze=False)
    tau = dict(a.tau.select("suite", "tau_b").iter_rows())
    small, large = A.backbone_label(a.small), A.backbone_label(a.large)
    for ax, suite in zip(axes.flat, a.suites):
        ranks = {
            b: dict(
                a.band.filter(pl.col("backbone") == b, pl.col("suite") == suite)
                .drop_nulls("rank")
                .select("encoder", "rank")
                .iter_rows()
            )
            for b in (a.small, a.large)
        }
        v = {r["source"]: r for r in a.verdicts.filter(pl.col("suite") == suite).iter_rows(named=True)}
        winners = {b: set((v[b]["source_winner"] or "").split(", ")) - {""} for b in (a.small, a.large)}
        tiers = {a.large: set(v[a.small]["target_band"] or []), a.small: set(v[a.large]["target_band"] or [])}
        shared = set(ranks[a.small]) & set(ranks[a.large])
        for enc in sorted(shared):
            won = (enc in winners[a.small], enc in winners[a.large])
            color = {(True, True): BOTH_WINNER_COLOR, (True, False): SMALL_WINNER_COLOR,
                     (False, True): LARGE_WINNER_COLOR}.get(won, "0.6")
            y = [ranks[a.small][enc], ranks[a.large][enc]]
            ax.plot([0, 1], y, color=color, lw=2.4 if any(won) else 1.2, zorder=2)
            for x, b, yy in ((0, a.small, y[0]), (1, a.large, y[1])):
                fill = color if enc in tiers[b] else "white"
                ax.scatter([x], [yy], s=40, zorder=3, edgecolors=color, facecolors=fill, linewidths=1.4)
        top = max([*ranks[a.small].values(), *ranks[a.large].values(), 1])
        ax.set_ylim(top + 0.5, 0.5)
        ax.set_xlim(-0.12, 1.12)
        _rank_ticks(ax, ranks[a.small], shared, number_first=False)
        right = ax.twinx()
        right.set_ylim(ax.get_ylim())
        _rank_ticks(right, ranks[a.large], shared, number_first=True)
        ax.set_xticks([0, 1], [small, large], fontsize=8)
        ax.set_xlabel("rank (1 = lowest mean MSE)", fontsize=7)
        t = "" if tau.get(suite) is None else f"   τb = {tau[suite]:.2f}"
        verdicts = f"{small} → {large}: {v[a.small]['verdict']}\n{large} → {small}: {v[a.large]['verdict']}"
        ax.set_title(f"{suite}{t}\n{verdicts}", fontsize=8)
    for ax in list(axes.flat)[len(a.suites) :]:
        ax.set_visible(False)
    fig.legend(
        handles=[
            Line2D([], [], color=SMALL_WINNER_COLOR, lw=2.4, label=f"{small} winner"),
            Line2D([], [], color=LARGE_WINNER_COLOR, lw=2.4, label=f"{large} winner"),
            Line2D([], [], color=BOTH_WINNER_COLOR, lw=2.4, label="winner on both"),
            Line2D([], [], ls="", marker="o", color="0.6", label="in that side's top tier"),
            Line2D([], [], ls="", marker="o", color="0.6", markerfacecolor="white", label="outside top tier"),
        ],
        loc="outside lower center",
        ncols=3 if cols > 1 else 2,
        fontsize=8,
        title="* = run on one backbone only",
        title_fontsize=7,
    )
    return fig


def figure_rank_bump(a: A.Analysis) -> Figure | None:
    """Bump chart per suite: every encoder's rank on each backbone of the ladder (smallest left), one line
    per encoder, broken where a backbone lacks it; a filled dot marks that backbone's top tier, so the rung
    where the ranking breaks shows as lines crossing. None with fewer than three backbones (two:
    figure_rank_transfer)."""
    ladder = a.ladder.backbones
    if len(ladder) < 3 or not len(a.band):
        return None
    rows, cols = grid(len(a.suites), max_cols=2)
    encoders = sorted(set(a.band["encoder"]))
    colors = {e: f"C{i % 10}" for i, e in enumerate(encoders)}
    n_enc = a.band.group_by(A.GROUP).len()["len"].max()
    fig = new_figure((1.1 * len(ladder) + 1.6) * cols, (0.35 * n_enc + 2.0) * rows)
    axes = fig.subplots(rows, cols, squeeze=False)
    for ax, suite in zip(axes.flat, a.suites):
        cells = a.band.filter(pl.col("suite") == suite).drop_nulls("rank")
        at = {(r["backbone"], r["encoder"]): r for r in cells.iter_rows(named=True)}
        for enc in encoders:
            ranks = [at[b, enc]["rank"] if (b, enc) in at else np.nan for b in ladder]
            ax.plot(range(len(ladder)), ranks, color=colors[enc], lw=1.8, zorder=2)
            for x, b in enumerate(ladder):
                if (b, enc) in at:
                    fill = colors[enc] if at[b, enc]["in_band"] else "white"
                    ax.scatter([x], [at[b, enc]["rank"]], s=40, zorder=3, edgecolors=colors[enc],
                               facecolors=fill, linewidths=1.4)
        top = max([*cells["rank"].to_list(), 1])
        ax.set_ylim(top + 0.5, 0.5)
        ax.set_yticks(range(1, top + 1))
        ax.set_xlim(-0.3, len(ladder) - 0.7)
        ax.set_xticks(range(len(ladder)), [A.backbone_label(b) for b in ladder], fontsize=8)
        ax.set_ylabel("rank (1 = best)", fontsize=8)
        ax.set_title(suite, fontsize=9)
    for ax in list(axes.flat)[len(a.suites):]:
        ax.set_visible(False)
    fig.legend(
        handles=[Line2D([], [], color=colors[e], lw=1.8, marker="o", label=e) for e in encoders],
        loc="outside lower center", ncols=min(len(encoders), 3), fontsize=8,
        title="filled dot = in that backbone's top tier; backbones by parameter count", title_fontsize=7,
    )
    return fig


def figure_controls(a: A.Analysis) -> Figure | None:
    """Per (backbone, suite): how much of each control's error the encoder removes,
    (mse_control - mse_enc) / mse_control in %, one marker per control; encoders whose MSE is within noise
    of zero-image are labelled in red. None when no control could be compared."""
    c = a.controls.drop_nulls("distance")
    if not len(c):
        return None
    backbones = [b for b in a.backbones if b in set(c["backbone"])]
    suites = sorted(set(c["suite"]))
    n_enc = c.group_by(A.GROUP).agg(pl.col("encoder").n_unique())["encoder"].max()
    fig = new_figure(4.2 * len(suites), (0.4 * n_enc + 1.4) * len(backbones))
    axes = fig.subplots(len(backbones), len(suites), squeeze=False)
    controls = sorted(set(c["control"]))
    colors = {k: CONTROL_COLORS.get(k, f"C{i + 2}") for i, k in enumerate(controls)}
    for ax, (backbone, suite) in zip(axes.flat, [(b, s) for b in backbones for s in suites]):
        cells = c.filter(pl.col("backbone") == backbone, pl.col("suite") == suite)
        if not len(cells):
            ax.set_visible(False)
            continue
        encs = sorted(set(cells["encoder"]))
        noisy = set(cells.filter(pl.col("control") == A.ZERO_IMAGE, pl.col("within_noise"))["encoder"])
        for i, k in enumerate(controls):
            sub = cells.filter(pl.col("control") == k)
            y = [encs.index(e) + (i - (len(controls) - 1) / 2) * 0.15 for e in sub["encoder"]]
            ax.scatter(100 * sub["distance"].to_numpy(), y, color=colors[k], s=30, zorder=3)
        ax.axvline(0, color="0.3", lw=0.8)
        ax.set_yticks(range(len(encs)), encs, fontsize=8)
        for tick, e in zip(ax.get_yticklabels(), encs):
            tick.set_color(SMALL_WINNER_COLOR if e in noisy else "black")
        ax.set_ylim(len(encs) - 0.5, -0.5)
        ax.set_xlabel("(control − encoder) / control  [%]", fontsize=8)
        ax.set_title(f"{A.backbone_label(backbone)} · {suite}", fontsize=9)
    fig.legend(
        handles=[Line2D([], [], ls="", marker="o", color=colors[k], label=k) for k in controls],
        loc="outside lower center",
        ncols=len(controls),
        fontsize=8,
        title="red encoder name = within noise of zero-image",
        title_fontsize=7,
    )
    return fig


def figure_blocks(a: A.Analysis, out: Path, name: str) -> list[Block]:
    """Draw the FIGURES figure `name` into `out` and return its Image block (none when there is nothing to
    draw)."""
    draw, caption = FIGURES[name]
    fig = draw(a)
    if fig is None:
        return []
    fig.savefig(out / name, dpi=110)
    return [Image(name, caption)]


FIGURES: dict[str, tuple[Callable[[A.Analysis], Figure | None], str]] = {
    "mse.png": (
        figure_mse,
        "Offline action MSE per encoder: mean (diamond, blue = top tier) with its min–max over seeds, and "
        "each seed as a dot; each panel's axis is fitted to its data.",
    ),
    "rank_transfer.png": (
        figure_rank_transfer,
        "Rank of each encoder on the small vs the large backbone; filled dots are in that side's top tier.",
    ),
    "rank_bump.png": (
        figure_rank_bump,
        ("Rank of each encoder on every backbone, smallest backbone left; filled dots are in that backbone's "
         "top tier."),
    ),
    "controls.png": (figure_controls, "Distance of each encoder from its controls (> 0: the encoder helps)."),
    "closed_loop.png": (figure_closed_loop, CLOSED_LOOP_CAPTION),
}
