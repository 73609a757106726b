"""Figures and the written report (report.md + report.html) from a results table.

The report is built once as a list of blocks (document.py) by sections (sections.py) that say things in
sentences (sentences.py) and tables (tables.py) and draw figures (figures.py), and rendered twice
(render.py), so the Markdown and the HTML can never say different things.
"""

from __future__ import annotations

import sys
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import polars as pl

from graftcache import analysis as A
from graftcache import results as R
from graftcache.report.closed_loop_csv import (
    CLOSED_LOOP_CSV,
    CLOSED_LOOP_CSV_COLUMNS,
    CLOSED_LOOP_CSV_SCHEMA,
    PAIRWISE_CSV,
    PAIRWISE_CSV_COLUMNS,
    PAIRWISE_CSV_SCHEMA,
    closed_loop_table,
    pairwise_table,
)
from graftcache.report.closed_loop_section import closed_loop_findings
from graftcache.report.document import Block, Heading, Image
from graftcache.report.figures import (
    FIGURES,
    figure_closed_loop,
    figure_controls,
    figure_mse,
    figure_rank_bump,
    figure_rank_transfer,
)
from graftcache.report.findings import beats_controls_sentences, reads_images_sentences
from graftcache.report.random_init import random_init_warning
from graftcache.report.render import render_html, render_markdown
from graftcache.report.sections import SECTIONS, header, provenance_section
from graftcache.report.sentences import (
    PROXY_NOTE,
    bootstrap_sentence,
    headline_sentences,
    stability_sentences,
    transfer_summary,
    verdict_sentences,
)
from graftcache.report.transfer_csv import TRANSFER_CSV, TRANSFER_CSV_COLUMNS, transfer_table

__all__ = [
    "CLOSED_LOOP_CSV", "CLOSED_LOOP_CSV_COLUMNS", "CLOSED_LOOP_CSV_SCHEMA", "closed_loop_table", "figure_closed_loop",
    "PAIRWISE_CSV", "PAIRWISE_CSV_COLUMNS", "PAIRWISE_CSV_SCHEMA", "pairwise_table",
    "FIGURES", "PROXY_NOTE", "TITLE", "TRANSFER_CSV", "TRANSFER_CSV_COLUMNS", "ReportPaths", "bootstrap_sentence",
    "figure_controls", "figure_mse", "figure_rank_bump", "figure_rank_transfer", "headline_sentences",
    "beats_controls_sentences", "reads_images_sentences", "random_init_warning", "render_html", "render_markdown",
    "report_command", "stability_sentences",
    "transfer_summary", "transfer_table", "verdict_sentences",
    "write_report",
]

TITLE = "graftcache report: does the encoder ranking transfer across backbones?"


@dataclass(frozen=True)
class ReportPaths:
    markdown: Path
    html: Path
    figures: tuple[Path, ...]
    transfer: Path  # transfer.csv: one row per verdict (graftcache.report.transfer_csv)
    notes: tuple[str, ...] = ()  # how the backbones were ordered where the rows did not say (also in the report)
    closed_loop: Path | None = None  # closed_loop.csv (graftcache.report.closed_loop_csv), given rollouts
    pairwise: Path | None = None  # pairwise.csv (graftcache.report.closed_loop_csv), given rollouts
    #: the closed-loop answers in lines, given rollouts (graftcache.report.closed_loop_section.closed_loop_findings)
    findings: tuple[str, ...] = ()


def write_report(
    results: pl.DataFrame | str | Path,
    out_dir: str | Path,
    *,
    commands: Mapping[str, str] | None = None,
    score: str = "mse",
    boot: A.BootSettings = A.BootSettings(),
    rollouts: str | Path | None = None,
) -> ReportPaths:
    """Analyse a results table (or Parquet path), ranked by `score` (graftcache.analysis.SCORES), and write
    report.md, report.html, PNG figures and transfer.csv to out_dir; given a rollouts Parquet file
    (graftcache.analysis.rollouts), the closed-loop section, closed_loop.csv and pairwise.csv too.

    The table needs only results.REPORT_COLUMNS; a path is read with results.read_for_report, so an absent,
    empty, non-Parquet or row-less file is a GraftcacheError naming it. `commands` (name -> command line)
    are cited at the top of the provenance section, e.g. the sweep and report invocations; every row's own
    `command` and `cache_key` are listed there too.
    """
    source = str(results) if isinstance(results, (str, Path)) else "in-memory table"
    table = R.read_for_report(results) if isinstance(results, (str, Path)) else results
    table = R.conform(table)
    episodes = None if rollouts is None else A.read_rollouts(rollouts, table)
    looks = None if rollouts is None else A.read_looks(rollouts)
    a = A.analyze(table, score=score, boot=boot, rollouts=episodes, looks=looks)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    for name in (*FIGURES, CLOSED_LOOP_CSV, PAIRWISE_CSV):  # a rerun must not leave a file the new report lacks
        (out / name).unlink(missing_ok=True)
    blocks: list[Block] = [Heading(TITLE, 1), *random_init_warning(a), *header(a, source)]
    for section in SECTIONS:
        blocks += section(a, out)
    blocks += provenance_section(a, commands)
    md, page = out / "report.md", out / "report.html"
    md.write_text(render_markdown(blocks, out), encoding="utf-8")
    page.write_text(render_html(blocks, out, TITLE), encoding="utf-8")
    transfer_table(a).write_csv(out / TRANSFER_CSV)
    closed = pairs = None
    if a.closed_loop is not None:
        closed, pairs = out / CLOSED_LOOP_CSV, out / PAIRWISE_CSV
        closed_loop_table(a).write_csv(closed)
        pairwise_table(a).write_csv(pairs)
    figures = tuple(out / b.name for b in blocks if isinstance(b, Image))
    return ReportPaths(md, page, figures, out / TRANSFER_CSV, a.ladder.notes, closed, pairs, closed_loop_findings(a))


def report_command(results_path: str | Path, out_dir: str | Path, *, command: str | None = None,
                   score: str = "mse", rollouts: str | Path | None = None) -> int:
    """`graftcache report RESULTS --out DIR [--score mse|ci-mse] [--rollouts PATH]`: write the report, print where
    it is, return the exit code.

    Every unusable results file is a GraftcacheError (the CLI prints it as one line); `command` is the
    exact invocation to cite in the report (the CLI passes its argv), defaulting to the canonical form.
    """
    path = Path(results_path)
    cited = command or f"graftcache report {path} --out {out_dir}"
    paths = write_report(path, out_dir, commands={"report": cited}, score=score, rollouts=rollouts)
    for note in paths.notes:
        print(f"note: {note}", file=sys.stderr)
    for line in paths.findings:
        print(line)
    written = [paths.markdown, paths.html, paths.transfer, *(p for p in (paths.closed_loop, paths.pairwise) if p)]
    print("report: " + "\n        ".join(map(str, written)))
    return 0
