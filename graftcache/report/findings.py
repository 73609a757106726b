"""The controls section's two findings, in words and one table: does each backbone read its images, and which
encoders beat both image controls on every seed (graftcache.analysis.findings). They lead the section because
they are what a demo's report must find: a policy blind to its images, or encoders no better than no image,
make every ranking above them moot."""

from __future__ import annotations

import polars as pl

from graftcache import analysis as A
from graftcache.report.document import Block, Bullets, Heading, Paragraph
from graftcache.report.tables import BEATS_COLUMNS, WEIGHTS, in_backbone_order, num, pct, table_block

READS_ABOUT = (
    "Its own vision tower, evaluated as loaded (`native`), against the zero-image control (every encoder's "
    "zero-image rows of that backbone and suite, pooled). 'Separated on every seed': the worst native seed is "
    "below the best zero-image seed. Relative gap = (zero-image mean − native mean) / zero-image mean."
)
BEATS_ABOUT = (
    "An encoder beats both image controls on every seed when its worst plain-graft seed is below the best "
    "zero-image seed and below the best shuffled-image seed of the same backbone, suite and encoder."
)


def _where(r: dict) -> str:
    return f"{A.backbone_label(r['backbone'])} · {r['suite']}"


def _counted(n: int, unit: str) -> str:
    return f"{n} {unit}" + ("" if n == 1 else "s")


def _side(r: dict, name: str, label: str, unit: str, extreme: tuple[str, str], of: str = "") -> str:
    """One side's mean over its rows and its extreme seed (the one the verdict compares); one row is just itself."""
    n, mean = r[f"{name}_n"], num(r[f"{name}_mean"])
    if n == 1:
        return f"{label} {mean} (1 {unit}{of})"
    which, column = extreme
    return f"{label} mean {mean} over {_counted(n, unit)}{of} ({which} {num(r[f'{name}_{column}'])})"


def reads_images_sentences(a: A.Analysis) -> list[str]:
    """One line per (backbone, suite): native against pooled zero-image, its verdict, or why there is none."""
    out = []
    for r in in_backbone_order(a, a.reads_images).iter_rows(named=True):
        if r["verdict"] is None:
            out.append(f"{_where(r)}: no verdict — {r['note']}.")
            continue
        native = _side(r, "native", "native", "seed", ("worst", "max"))
        zero = _side(r, "zero", "zero-image", "row", ("best", "min"), f" of {r['zero_encoders']}")
        text = f"{_where(r)}: {r['verdict']} — {native} vs {zero}; relative gap {pct(r['gap'])}."
        out.append(text + (f" [{r['note']}]" if r["note"] else ""))
    return out


def beats_controls_sentences(a: A.Analysis) -> list[str]:
    """One line per backbone: the encoders (and suites) that beat both image controls on every seed, or plainly
    that none does, with how many encoder-suite cells could be judged."""
    frame = in_backbone_order(a, a.beats_controls)
    out = []
    for b in frame["backbone"].unique(maintain_order=True).to_list():
        rows = frame.filter(pl.col("backbone") == b)
        judged = rows.drop_nulls("verdict")
        wins = judged.filter(pl.col("verdict") == A.BEATS_BOTH)
        lacking = len(rows) - len(judged)
        count = (f"{len(wins)} of {len(judged)} judged encoder-suite cells"
                 + (f"; {lacking} cannot be judged for missing rows" if lacking else ""))
        who = [f"{r['encoder']} on {r['suite']} ({WEIGHTS[r['encoder_random_init']]} weights"
               + ("; one seed" if r["note"] else "") + ")" for r in wins.iter_rows(named=True)]
        label = A.backbone_label(b)
        if who:
            out.append(f"{label}: {', '.join(who)} beat{'s' if len(who) == 1 else ''} both image controls on every "
                       f"seed ({count}).")
        elif len(judged):
            out.append(f"{label}: no encoder beats both image controls on every seed ({count}).")
        else:
            out.append(f"{label}: no encoder-suite cell can be judged: all {lacking} lack plain-graft, zero-image "
                       "or shuffled-image rows.")
    return out


def findings_blocks(a: A.Analysis) -> list[Block]:
    """Both findings: the native-vs-zero-image lines, then the per-backbone lines and the per-encoder table."""
    reads = reads_images_sentences(a)
    blocks: list[Block] = [Heading("Does each backbone read its images?", 3), Paragraph(READS_ABOUT), (
        Bullets(tuple(reads)) if reads
        else Paragraph("No `native` or `zero-image` rows in the table: this cannot be judged.")
    ), Heading("Which encoders beat both image controls on every seed?", 3), Paragraph(BEATS_ABOUT)]
    shown = in_backbone_order(a, a.beats_controls.filter((pl.col("zero_n") > 0) | (pl.col("shuffled_n") > 0)))
    if not len(shown):
        return [*blocks, Paragraph("No `zero-image` or `shuffled-image` rows in the table: this cannot be judged.")]
    blocks += [Bullets(tuple(beats_controls_sentences(a))), table_block(shown, BEATS_COLUMNS)]
    if hidden := len(a.beats_controls) - len(shown):
        blocks.append(Paragraph(f"{_counted(hidden, 'encoder-suite cell')} with neither image control not shown."))
    return blocks
