"""The report's dose-response section (only where the results hold `noise-A` rows): per encoder, offline MSE and
closed-loop progress at each dose, whether each curve is monotone, and the resolution: the finest offline eval_mse
gap between adjacent doses that the closed loop confirms at the episodes spent (graftcache.analysis.dose)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from graftcache import analysis as A
from graftcache.report.document import Block, Bullets, Heading, Image, Paragraph
from graftcache.report.dose_figure import DOSE_CAPTION, figure_dose
from graftcache.report.tables import BACKBONE, Column, Row, col, in_backbone_order, num, table_block

FIGURE = "dose.png"
ABOUT = (
    "Each encoder's features are degraded in known steps (noise-A: √(1−A)·f + √A·σ·ε, σ the features' per-channel "
    "spread on the training split; A = 0 is the plain graft, A = 1 the zero-image control) and every dose is fitted, "
    "scored offline and rolled out like any cell. Offline: eval_mse, mean over seeds with a 95% t interval. Closed "
    "loop: the closest approach to the target, mean over every episode of the dose's seeds with a 95% t interval. "
    "Between adjacent doses both differences are paired (offline by fit seed; closed loop by fit seed and episode "
    "key) with 95% t intervals; the closed loop confirms a step when its interval excludes 0 in the direction the "
    "offline difference has. A curve is monotone when every step moves towards blindness, monotone within noise when "
    "every step against it is unresolved. The resolution is the smallest offline gap the closed loop confirms."
)


def _interval(mean: str, lo: str, hi: str, fmt: str = ".4g") -> Callable[[Row], str]:
    """A mean with its interval, as the tables write it; null -> '—'."""

    def cell(r: Row) -> str:
        if r[mean] is None:
            return "—"
        span = "" if r[lo] is None else f" [{r[lo]:{fmt}}, {r[hi]:{fmt}}]"
        return f"{r[mean]:{fmt}}{span}"
    return cell


def _resolves(r: Row) -> str:
    """Whether the offline difference's interval excludes 0 (a confirmed step need not be resolved offline)."""
    if r["offline_lo"] is None:
        return "—"
    return "yes" if r["offline_lo"] > 0 or r["offline_hi"] < 0 else "no"


POINT_COLUMNS: tuple[Column, ...] = (
    BACKBONE, ("suite", col("suite")), ("encoder", col("encoder")), ("dose", col("dose", lambda x: f"{x:g}")),
    ("control", col("control")), ("seeds", col("seeds")),
    ("eval_mse (95% t)", _interval("offline_mean", "offline_lo", "offline_hi")),
    ("episodes", col("episodes")),
    ("closest approach m (95% t)", _interval("loop_mean", "loop_lo", "loop_hi", ".3f")),
)
STEP_COLUMNS: tuple[Column, ...] = (
    BACKBONE, ("suite", col("suite")), ("encoder", col("encoder")),
    ("step", lambda r: f"{r['dose_from']:g} → {r['dose_to']:g}"),
    ("Δ eval_mse (95% t, seeds)", _interval("offline_diff", "offline_lo", "offline_hi")),
    ("Δ closest approach m (95% t, pairs)", _interval("loop_diff", "loop_lo", "loop_hi", ".3f")),
    ("offline resolves", _resolves), ("pairs", col("loop_pairs")),
    ("confirmed", col("confirmed", lambda x: "yes" if x else "no")),
)


def resolution_sentence(r: Row) -> str:
    """One curve's verdicts in words."""
    name = f"{A.backbone_label(r['backbone'])} / {r['suite']} / {r['encoder']} ({r['doses']} doses)"
    shape = (f"offline {r['offline_monotone'] or 'without a measured step'}, closed loop "
             f"{r['loop_monotone'] or 'without a measured step'}")
    if r["resolution"] is None:
        return f"{name}: {shape}; resolution undefined: {r['note']}."
    return (f"{name}: {shape}; resolution {num(r['resolution'], '.3g')} eval_mse (the smallest offline gap between "
            "adjacent doses that the closed loop confirms).")


def dose_section(a: A.Analysis, out: Path) -> list[Block]:
    """The dose curves (nothing without `noise-A` rows)."""
    if a.dose is None:
        return []
    blocks: list[Block] = [Heading("Dose response: what offline MSE resolves in the closed loop"), Paragraph(ABOUT),
                           Bullets(tuple(resolution_sentence(r)
                                         for r in in_backbone_order(a, a.dose.curves).iter_rows(named=True)))]
    fig = figure_dose(a)
    if fig is not None:
        fig.savefig(out / FIGURE, dpi=110)
        blocks.append(Image(FIGURE, DOSE_CAPTION))
    return [*blocks, Heading("Doses", 3), table_block(in_backbone_order(a, a.dose.points), POINT_COLUMNS),
            Heading("Adjacent doses, paired", 3), table_block(in_backbone_order(a, a.dose.steps), STEP_COLUMNS)]
