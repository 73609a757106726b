"""The report's sections, in reading order: each turns one Analysis into blocks (and draws its figures)."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from datetime import UTC, datetime
from pathlib import Path

import polars as pl

from graftcache import analysis as A
from graftcache import results as R
from graftcache.critical import WINDOW
from graftcache.report.closed_loop_section import closed_loop_section
from graftcache.report.document import Alert, Block, Bullets, Heading, Paragraph
from graftcache.report.dose_section import dose_section
from graftcache.report.figures import figure_blocks
from graftcache.report.findings import findings_blocks
from graftcache.report.sentences import (
    PROXY_NOTE,
    SEED_LEVEL_BOOTSTRAP,
    bootstrap_sentence,
    by_halves,
    direction,
    headline_sentences,
    score_sentence,
    stability_sentences,
    transfer_summary,
    verdict_sentences,
)
from graftcache.report.tables import (
    CONTROL_COLUMNS,
    MISSING_COLUMNS,
    MSE_COLUMNS,
    PROVENANCE_COLUMNS,
    SCORE_COLUMNS,
    SEED_COLUMNS,
    WRAPPER_COLUMNS,
    in_backbone_order,
    ladder_block,
    table_block,
    tau_matrix_block,
    transfer_columns,
)


def header(a: A.Analysis, source: str) -> list[Block]:
    """What the table holds: rows, backbones, suites, encoders, versions, and what it lacks."""
    r = a.results

    def listed(values: object) -> str:
        return ", ".join(sorted(set(values))) or "—"

    have, total = a.episode_coverage
    empty = [c for c in R.SCHEMA if len(r) and r[c].null_count() == len(r)]
    params = a.ladder.params
    facts = (
        f"Results: `{source}` ({len(r)} rows).",
        "Backbones, by parameter count: " + (", ".join(
            f"{A.backbone_label(b)} (`{b}`" + (f", {A.format_params(params[b])})" if b in params else ")")
            for b in a.backbones) or "none") + ".",
        *(f"Backbone order: {note}." for note in a.ladder.notes),
        f"Score: {A.SCORE_LABELS[a.score]} (`--score {a.score}`).",
        f"Suites: {listed(a.suites)}.",
        f"Encoders: {listed(a.band['encoder'])}.",
        (f"graftcache versions: {listed(r['graftcache_version'].drop_nulls())}; "
         f"devices: {listed(r['device'].drop_nulls())}."),
        "Per-episode MSEs: " + (
            f"all {total} cells." if have == total
            else f"none ({SEED_LEVEL_BOOTSTRAP}, see Method)." if not have
            else f"{have} of {total} cells ({SEED_LEVEL_BOOTSTRAP} for the rest, see Method)."
        ),
        *([f"Columns without values (absent or all null): {', '.join(empty)}."] if empty else []),
        f"Generated {datetime.now(UTC):%Y-%m-%d %H:%M UTC}.",
    )
    return [Bullets(facts), Paragraph(PROXY_NOTE)]


def _transfer_section(a: A.Analysis, out: Path) -> list[Block]:
    head = Heading("Does the ranking transfer?")
    if a.transfer_gap:
        return [head, Paragraph(f"The transfer question {a.transfer_gap}, so no verdict is given.")]
    if len(a.ladder.backbones) == 2:  # the paper's framing: one small and one large backbone
        return [
            head, Paragraph(transfer_summary(a)), Bullets(tuple(verdict_sentences(a))), *_stability(a),
            table_block(a.verdicts, transfer_columns(a)), *figure_blocks(a, out, "rank_transfer.png"),
        ]
    about = ("Backbones stand on a ladder by parameter count; each rung is a backbone and the next larger one. "
             "Every pair is judged in both directions below.")
    taus: list[Block] = []
    for suite in a.suites:
        taus += [Paragraph(f"Kendall τb between the backbones' mean MSEs, {suite}:"), tau_matrix_block(a, suite)]
    return [
        head, Paragraph(about), ladder_block(a), Bullets(tuple(headline_sentences(a))),
        *figure_blocks(a, out, "rank_bump.png"),
        Paragraph(transfer_summary(a)), Bullets(tuple(verdict_sentences(a))), *_stability(a),
        table_block(a.verdicts, transfer_columns(a)), *taus,
    ]


def _stability(a: A.Analysis) -> list[Block]:
    """Would a rerun with other seeds keep these verdicts? Each judged comparison repeated on parts of the seeds."""
    parts = f"each half of the seeds (with {A.HALVES_FROM} seeds or more)" if by_halves(a) else "each seed alone"
    about = (f"Seed stability: every judged comparison repeated on {parts}; a verdict holds under a part when the "
             "part gives the same verdict and the same target top tier as all seeds.")
    return [Paragraph(about), Bullets(tuple(stability_sentences(a)))]


def _score_section(a: A.Analysis, _: Path) -> list[Block]:
    if not len(a.scores):
        return []
    about = ("CI-MSE is the action error on the chunk steps within "
             f"±{WINDOW} steps of a gripper open/close transition (graftcache/critical.py).")
    return [Heading("MSE and CI-MSE: where the rankings disagree"), Paragraph(about), Paragraph(score_sentence(a)),
            table_block(in_backbone_order(a, a.scores), SCORE_COLUMNS)]


def _mse_section(a: A.Analysis, out: Path) -> list[Block]:
    head = Heading("Offline action MSE per backbone and suite")
    if not len(a.band):
        return [head, Paragraph("No plain-graft rows (control `none`) in the table.")]
    return [head, *figure_blocks(a, out, "mse.png"), table_block(in_backbone_order(a, a.band), MSE_COLUMNS)]


def _seed_section(a: A.Analysis, _: Path) -> list[Block]:
    if a.transfer_gap or not len(a.seed_verdicts):
        return []
    about = (
        "Each comparison repeated on one seed's rows alone: is the source backbone's top-1 at seed s in the "
        "target backbone's top tier at seed s? With one seed per cell that tier rests on the seed's held-out "
        "episodes when rows carry them, and is the exact ties of the best otherwise (basis column)."
    )
    return [Heading("Seed-level agreement"), Paragraph(about), table_block(a.seed_verdicts, SEED_COLUMNS)]


def _wrapper_section(a: A.Analysis, _: Path) -> list[Block]:
    about = (
        "(mse(native-graft) − mse(native)) / mse(native): the cost of routing the backbone's own vision "
        "tower through the graft wrapper (pass-through tower + fitted projector); 0 means the wrapper is "
        "neutral."
    )
    body = (
        table_block(in_backbone_order(a, a.wrapper), WRAPPER_COLUMNS) if len(a.wrapper)
        else Paragraph("No `native` or `native-graft` rows in the table.")
    )
    return [Heading("Wrapper non-neutrality"), Paragraph(about), body]


def _controls_section(a: A.Analysis, out: Path) -> list[Block]:
    head = [Heading("Controls: does the encoder matter?"), *findings_blocks(a),
            Heading("Each encoder's distance from each control", 3)]
    have = in_backbone_order(a, a.controls.filter(pl.col("control_n") > 0))
    if not len(have):
        return [*head, Paragraph(
            "No encoder-level control rows (zero-image, shuffled-image, pool-HxW, lora)."
        )]
    about = (
        "distance = (mse_control − mse_encoder) / mse_control: the share of the control's error the encoder "
        f"removes. 'within noise' = the encoder is not better than the control at {a.boot.confidence:.0%} "
        "under the seed bootstrap."
    )
    blocks: list[Block] = [*head, Paragraph(about)]
    noisy = have.filter(pl.col("control") == A.ZERO_IMAGE, pl.col("within_noise")).select(A.CELL).rows()
    if noisy:
        lines = tuple(f"{A.backbone_label(b)} · {s} · {e}: the image features add nothing measurable"
                      for b, s, e in noisy)
        blocks.append(Alert("encoders within noise of zero-image", lines))
    blocks += [*figure_blocks(a, out, "controls.png"), table_block(have, CONTROL_COLUMNS)]
    if lacking := len(a.controls) - len(have):
        blocks.append(Paragraph(f"{lacking} (encoder, control) pairs have no control rows (not shown)."))
    return blocks


def _missing_section(a: A.Analysis, _: Path) -> list[Block]:
    if not len(a.missing):
        return []
    about = "Gaps in the plain-graft grid; the tables above show them as '—' or 'insufficient data'."
    gaps = table_block(in_backbone_order(a, a.missing), MISSING_COLUMNS)
    return [Heading("Missing cells"), Paragraph(about), gaps]


def _transfer_method(a: A.Analysis) -> str:
    """How a transfer is judged, in the paper's words for its two backbones, generally for a ladder."""
    if len(a.ladder.backbones) != 2:
        return ("Transfer, for every pair of backbones and in both directions: the source backbone's winner(s), "
                "among encoders run on both, must all be in the target's top tier. A target top tier holding "
                f"every shared encoder separates nothing: a seed-sensitive '{A.NEAR_TIE}', not a transfer. "
                "Backbones are ordered by parameter count (`backbone_params`); the ranking breaks at the first "
                "rung (a backbone and the next larger one) whose upward verdict is "
                f"'{A.DOES_NOT_TRANSFER}'. Seed-level cells repeat each comparison on one seed's rows; counts "
                f"('k of n') leave out '{A.INSUFFICIENT}'.")
    small, large = A.backbone_label(a.small), A.backbone_label(a.large)
    return (f"Transfer, in both directions: the {small} winner(s), among encoders run on both backbones, must "
            f"all be in the {large} top tier ({direction(a.small, a.large)}), and the {large} winner(s) in the "
            f"{small} top tier ({direction(a.large, a.small)}). A target top tier holding every shared encoder "
            f"separates nothing, so that comparison is a seed-sensitive '{A.NEAR_TIE}', not a transfer. "
            "Seed-level cells repeat each comparison on one seed's rows; counts ('k of n') leave out "
            f"'{A.INSUFFICIENT}'.")


def _methods_section(a: A.Analysis, _: Path) -> list[Block]:
    pairs = "the two backbones'" if len(a.ladder.backbones) == 2 else "every two backbones'"
    return [Heading("Method"), Bullets((
        PROXY_NOTE,
        ("Per (backbone, suite, encoder): mean, std (ddof=1), min and max of eval_mse over seeds; "
         "rank 1 = lowest mean, equal means share a rank."),
        (f"Top tier: encoder e is in it unless P(mean_e* > mean_best*) ≥ {a.boot.confidence:.2f} "
         f"over {a.boot.n_boot} bootstrap replicates (seed {a.boot.seed}). With one seed and no per-episode "
         "MSEs the tier is the exact ties of the best (flagged)."),
        bootstrap_sentence(a),
        _transfer_method(a),
        f"Kendall τb (ties corrected) between {pairs} mean MSEs over the shared encoders.",
    ))]


def provenance_section(a: A.Analysis, commands: Mapping[str, str] | None) -> list[Block]:
    blocks: list[Block] = [Heading("Provenance: commands and cache keys behind every number")]
    if commands:
        blocks.append(Bullets(tuple(f"{k}: `{v}`" for k, v in commands.items())))
    rows = in_backbone_order(a, a.results.sort("backbone", "suite", "encoder", "control", "seed"))
    return [*blocks, table_block(rows, PROVENANCE_COLUMNS)]


SECTIONS: tuple[Callable[[A.Analysis, Path], list[Block]], ...] = (
    _transfer_section, _mse_section, _score_section, _seed_section, _wrapper_section, _controls_section,
    closed_loop_section, dose_section, _missing_section, _methods_section,
)
