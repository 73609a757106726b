"""The report's closed-loop section (only with `report --rollouts`): the validity figure's numbers in words and
tables. First, prominently, how well eval_mse orders the candidate encoders (plain grafts) by their closest
approach to the target (the graded measure the sample's reach -> grasp -> lift policies move first), the question
a user brings; then the same over every distinct policy, controls included (does looking help?); then the pairwise
verdicts, the table a user picking an encoder reads; then the native tower against zero-image on the same
episodes; then the figure, every (cells, score, measure) agreement and every cell."""

from __future__ import annotations

from pathlib import Path

import polars as pl

from graftcache import analysis as A
from graftcache.report.closed_loop_pairwise import pairwise_blocks, pairwise_lines
from graftcache.report.document import Block, Bullets, Heading, Paragraph
from graftcache.report.dose_section import resolution_sentence
from graftcache.report.figures import figure_blocks
from graftcache.report.tables import BACKBONE, NOTE, Column, Row, col, in_backbone_order, num, table_block

#: The headline pair: the offline score and the graded measure the report prints first
HEADLINE_SCORE, HEADLINE_MEASURE = "eval_mse", "min_target_distance_m"
#: How the report names each measure, and its unit
MEASURE_LABELS = {"success": "success", "min_target_distance_m": "closest approach",
                  "final_target_distance_m": "final distance", "target_lift_m": "target lift", "grasped": "grasped",
                  "goal_fraction": "goal fraction"}
UNITS = {"min_target_distance_m": " m", "final_target_distance_m": " m", "target_lift_m": " m"}
ABOUT = (
    "A cell is one policy that was rolled out (one seed of an encoder or control; results rows that hold the same "
    "policy, such as a zero-image control under several encoders, are one cell, their episodes pooled and each "
    "episode key counted once): its success rate over its episodes, with a 95% Wilson score interval, and the mean of "
    "each graded measure over its episodes that record it. Agreement is computed over policies, not over seed means: "
    "a policy is what was scored offline and rolled out, so its score and its closed-loop value are one paired "
    "measurement. Two agreements per backbone and suite: over the candidates (plain grafts: does the offline score "
    "order the encoders as the closed loop does?) and over every policy with the controls (does looking help?). Per "
    "offline score (lower is better) and closed-loop measure: Spearman ρ and Kendall τb of −score against the "
    "measure oriented so that higher is better (distances negated), so positive means lower scores go with a better "
    "closed loop for every measure; and MMRV (SIMPLER, arXiv 2405.05941: with proxy S = −score and the oriented "
    "measure R, (1/N) Σ_i max_j |R_i − R_j| [(S_i < S_j) ≠ (R_i < R_j)], in the measure's units, 0 when no pair is "
    "misordered). Each has a 95% interval from {n_boot} bootstrap replicates that redraw the cells and, within each "
    "drawn cell, its episodes (seed {seed}). `eval_mse_arm` is the error on the first action_dim − 1 dimensions "
    "(LIBERO's end effector), `eval_mse_gripper` on the last."
)
UNDEFINED = (
    "A figure shown as — (empty in closed_loop.csv) is undefined, never 0: with fewer than 2 cells, where every cell "
    "has the same value of the measure (e.g. every episode failed: no order to agree with), or where no episode "
    "records a graded measure; ρ and τb also where every cell has the same score. The note says which. Intervals "
    "are taken over the replicates in which the drawn cells do not all tie (`replicates` in closed_loop.csv)."
)
INTERVALS = (
    "Each interval says how far the figure moves when other policies of the same kind are drawn and each one's "
    "episodes are redrawn: the figure ± the 95% quantile of the replicates' distance from it, clipped to the "
    "statistic's range. Episode noise blurs an order more often than it sharpens one, so the replicates lean towards "
    "weaker agreement; their percentiles can then leave out the figure itself, and this interval cannot."
)
PAIRING = (
    "Per episode key (suite, task, episode, seed, step limit, perturbation) run by both sides: the mean over the "
    "native cells minus the mean over the zero-image cells (every distinct policy); then the mean of these paired "
    "differences over the keys, with a 95% bootstrap interval over the keys. The native tower is better when the "
    "whole interval lies on its better side; the seed count says on how many native seeds alone it is."
)


def _unit(measure: str) -> str:
    return UNITS.get(measure, "")


def _with_interval(r: Row, name: str, fmt: str, unit: str = "") -> str:
    if r[name] is None:
        return "—"
    low = "" if r[f"{name}_low"] is None else f" [{r[f'{name}_low']:{fmt}}, {r[f'{name}_high']:{fmt}}]"
    return f"{r[name]:{fmt}}{unit}{low}"


def _rate(r: Row) -> str:
    return f"{r['success_rate']:.0%} [{r['ci_low']:.0%}, {r['ci_high']:.0%}]"


def recorded_measures(loop: A.ClosedLoop) -> list[str]:
    """Success and every graded measure that at least one cell records, in MEASURES order."""
    return [m for m in A.MEASURES if loop.cells[A.MEASURE_COLUMNS[m]].is_not_null().any()]


def ungraded_sentence(loop: A.ClosedLoop) -> str | None:
    """What the report says of episodes without graded measures (format-1 rows, or a user's table without the
    columns): they are counted, never dropped, and their graded figures are undefined."""
    missing, total = loop.ungraded, len(loop.rollouts)
    if not missing:
        return None
    if missing == total:
        return (f"The graded measures are unavailable for these rollouts: none of the {total} episodes records them "
                "(format-1 rollouts rows, or a table without the graded columns), so only success is set against "
                "the offline scores; their rows in closed_loop.csv are empty, and undefined for this reason.")
    return (f"The graded measures are unavailable for {missing} of {total} episodes (format-1 rollouts rows, or a "
            "table without the graded columns): each cell's graded means are over the episodes that record them "
            "(`graded episodes`), and a cell without any has none.")


def kernels_sentence(loop: A.ClosedLoop) -> str | None:
    """What the report says of episodes computed on more than one set of kernels (`rollout --device`, another CPU):
    an action on other kernels differs in its last bits and the episode after it may drift, so cells compared across
    them hold that drift beside their difference. Nothing where every episode records the same kernels, or none."""
    kernels = loop.kernels
    if len(kernels) < 2:
        return None
    counts = ", ".join(f"{name or 'not recorded'}: {n}" for name, n in kernels.items())
    return (f"These episodes' policies computed on {len(kernels)} sets of kernels (episodes: {counts}; the rollouts "
            "column `kernels`). An action computed on other kernels differs in its last bits and its episode may "
            "drift from there, so a difference between cells rolled out on different kernels holds that drift too "
            "(`benchmarks/gpu_closed_loop.py` measures it for one pair of paths); roll the cells compared out on one "
            "device to leave it out.")


def headline_sentences(loop: A.ClosedLoop, cells_of: str, *, rolled_only: bool = False) -> list[str]:
    """eval_mse against the closest approach over `cells_of` (graftcache.analysis.CELLS_OF), per backbone and
    suite, with intervals or why undefined; `rolled_only`: only the (backbone, suite)s with cells of `cells_of`
    rolled out (a command's printout leaves out the others, which the report lists)."""
    rows = loop.agreement.filter(pl.col("cells_of") == cells_of, pl.col("score") == HEADLINE_SCORE,
                                 pl.col("measure") == HEADLINE_MEASURE)
    if rolled_only:
        rows = rows.filter(pl.col("cells") > 0)
    out = []
    for r in rows.iter_rows(named=True):
        where = f"{A.backbone_label(r['backbone'])} · {r['suite']} · {cells_of}"
        if r["mmrv"] is None:
            out.append(f"{where}: undefined over {r['cells']} cells ({r['note']}).")
            continue
        cells = loop.cells.filter(pl.col("backbone") == r["backbone"], pl.col("suite") == r["suite"],
                                  pl.col(HEADLINE_SCORE).is_finite(), pl.col(HEADLINE_MEASURE).is_not_null())
        if cells_of == A.CANDIDATES:
            cells = cells.filter(pl.col("control") == A.PLAIN)
        lo, hi = cells["graded_episodes"].min(), cells["graded_episodes"].max()
        each = f"{lo}" if lo == hi else f"{lo}–{hi}"
        rho = f"Spearman ρ = {_with_interval(r, 'spearman', '+.2f')}" if r["spearman"] is not None else "ρ —"
        tau = f"Kendall τb = {_with_interval(r, 'kendall_tau_b', '+.2f')}" if r["kendall_tau_b"] is not None else "τb —"
        out.append(f"{where}: {rho}, {tau}, MMRV = {_with_interval(r, 'mmrv', '.3g', ' m')} over {r['cells']} cells "
                   f"({each} episodes each)" + (f"; {r['note']}" if r["note"] else "") + ".")
    return out


def control_sentence(r: Row) -> str:
    """One paired control row in words."""
    label, unit = MEASURE_LABELS[r["measure"]], _unit(r["measure"])
    where = f"{A.backbone_label(r['backbone'])} · {r['suite']} · {label}"
    if r["difference"] is None:
        return f"{where}: undefined ({r['note']})."
    text = (f"{where}: native tower {r['native']:.3g}{unit} vs zero-image {r['zero_image']:.3g}{unit} on "
            f"{r['pairs']} paired episodes ({r['native_cells']} native, {r['zero_image_cells']} zero-image cells): "
            f"native − zero-image = {r['difference']:+.3g}{unit}")
    if r["ci_low"] is None:
        return f"{text}; {r['note']}."
    side = "higher" if A.HIGHER_IS_BETTER[r["measure"]] else "lower"
    verdict = {A.NATIVE_BETTER: "the native tower is better", A.ZERO_IMAGE_BETTER: "zero-image is better",
               A.NOT_SEPARATED: "not separated (the interval holds 0)"}[r["better"]]
    return (f"{text} [{r['ci_low']:+.3g}, {r['ci_high']:+.3g}]: {verdict} ({side} is better); the native tower is "
            f"better on {r['native_seeds_better']} of {r['native_seeds']} native seeds.")


AGREEMENT_COLUMNS: tuple[Column, ...] = (
    BACKBONE, ("suite", col("suite")), ("cells of", col("cells_of")), ("measure", col("measure")),
    ("score", lambda r: f"`{r['score']}`"), ("cells", col("cells")),
    ("Spearman ρ [95%]", lambda r: _with_interval(r, "spearman", "+.2f")),
    ("Kendall τb [95%]", lambda r: _with_interval(r, "kendall_tau_b", "+.2f")),
    ("MMRV [95%]", lambda r: _with_interval(r, "mmrv", ".3g", _unit(r["measure"]))), NOTE,
)
LOOP_CONTROL_COLUMNS: tuple[Column, ...] = (
    BACKBONE, ("suite", col("suite")), ("measure", col("measure")), ("native cells", col("native_cells")),
    ("zero-image cells", col("zero_image_cells")), ("paired episodes", col("pairs")),
    ("native", col("native", num)), ("zero-image", col("zero_image", num)),
    ("native − zero-image [95%]", lambda r: "—" if r["difference"] is None else f"{r['difference']:+.3g}" + (
        "" if r["ci_low"] is None else f" [{r['ci_low']:+.3g}, {r['ci_high']:+.3g}]")),
    ("better", col("better")),
    ("native seeds better", lambda r: "—" if r["difference"] is None else
     f"{r['native_seeds_better']} of {r['native_seeds']}"), NOTE,
)


def cell_columns(measures: list[str]) -> tuple[Column, ...]:
    """The cells table: identity, episodes, success with its interval, the recorded graded means, the scores."""
    graded = [m for m in measures if m != "success"]
    return (
        BACKBONE, ("suite", col("suite")), ("encoder", col("encoder")), ("control", col("control")),
        ("seed", col("seed")), ("run_id", col("run_id", lambda x: f"`{x}`")), ("rows", col("runs")),
        ("episodes", col("episodes")),
        ("success (95% Wilson)", _rate),
        *((("graded episodes", col("graded_episodes")),) if graded else ()),
        *((f"{MEASURE_LABELS[m]}{' (m)' if m in UNITS else ''}", col(A.MEASURE_COLUMNS[m], num)) for m in graded),
        *((s, col(s, num)) for s in A.CLOSED_LOOP_SCORES),
    )


def closed_loop_findings(a: A.Analysis) -> tuple[str, ...]:
    """The closed-loop answers in lines, for a command to print (the report says each at length): the candidates'
    agreement, the pairwise verdicts, the dose family's resolution; nothing without rollouts."""
    if a.closed_loop is None or not len(a.closed_loop.cells):
        return ()
    doses = () if a.dose is None else in_backbone_order(a, a.dose.curves).iter_rows(named=True)
    return (*headline_sentences(a.closed_loop, A.CANDIDATES, rolled_only=True),
            *pairwise_lines(a, HEADLINE_MEASURE, _unit(HEADLINE_MEASURE)),
            *(resolution_sentence(r) for r in doses))


def closed_loop_section(a: A.Analysis, out: Path) -> list[Block]:
    """Offline scores against the closed loop (only with `report --rollouts`)."""
    if a.closed_loop is None:
        return []
    loop, head = a.closed_loop, Heading("Offline scores vs closed-loop success")
    if not len(loop.cells):
        return [head, Paragraph("No results row has rollouts.")]
    measures = recorded_measures(loop)
    blocks: list[Block] = [head, Paragraph(ABOUT.format(n_boot=A.N_BOOT, seed=a.boot.seed))]
    for sentence in (ungraded_sentence(loop), kernels_sentence(loop)):
        if sentence:
            blocks.append(Paragraph(sentence))
    blocks += [Heading(f"Candidates: does `{HEADLINE_SCORE}` order the encoders as the closest approach to the target "
                       f"(`{HEADLINE_MEASURE}`) does?", 3),
               Bullets(tuple(headline_sentences(loop, A.CANDIDATES))),
               Heading("With controls: does looking help?", 3),
               Bullets(tuple(headline_sentences(loop, A.WITH_CONTROLS))), Paragraph(INTERVALS),
               Heading("Which encoder wins? Pairwise verdicts", 3),
               *pairwise_blocks(a, HEADLINE_MEASURE, MEASURE_LABELS[HEADLINE_MEASURE], _unit(HEADLINE_MEASURE))]
    control = loop.control.filter(pl.col("measure").is_in(measures),
                                  (pl.col("native_cells") > 0) | (pl.col("zero_image_cells") > 0))
    blocks += [Heading("Native tower vs zero-image on the same episodes", 3), Paragraph(PAIRING)]
    lines = loop.control.filter(pl.col("measure").is_in([HEADLINE_MEASURE, "success"]),
                                pl.col("measure").is_in(measures))
    blocks.append(Bullets(tuple(control_sentence(r) for r in in_backbone_order(a, lines).iter_rows(named=True))))
    if len(control):
        blocks.append(table_block(in_backbone_order(a, control), LOOP_CONTROL_COLUMNS))
    agreement = loop.agreement.filter(pl.col("measure").is_in(measures))
    return [*blocks, *figure_blocks(a, out, "closed_loop.png"),
            Heading("Every score against every measure, over the candidates and with controls", 3),
            Paragraph(UNDEFINED), table_block(in_backbone_order(a, agreement), AGREEMENT_COLUMNS),
            Heading("Cells", 3), table_block(in_backbone_order(a, loop.cells), cell_columns(measures))]
