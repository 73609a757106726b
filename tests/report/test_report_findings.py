"""The controls section's two findings (graftcache.report.findings) on tests/helpers/findings.py's table."""

from __future__ import annotations

import pytest
from helpers.findings import findings_table
from helpers.tables import full_table, plain_rows, table

from graftcache import analysis, report

QUICK = analysis.BootSettings(n_boot=50)

READS = (
    ("SmolVLA · s: separated on every seed — native mean 1.05 over 2 seeds (worst 1.1) vs zero-image mean 2.15 over "
     "4 rows of a, b (best 2); relative gap +51.2%."),
    ("pi0.5 · s: not separated — native mean 1.55 over 2 seeds (worst 2.1) vs zero-image mean 2.5 over 2 rows of a "
     "(best 2); relative gap +38.0%."),
    "pi0.5 · t: no verdict — no valid zero-image rows.",
    "SmolVLA · t: no verdict — no valid native rows.",
    ("SmolVLA · u: separated on every seed — native 1 (1 seed) vs zero-image 3 (1 row of a); relative gap +66.7%. "
     "[one seed: native (seed 0), zero-image (seed 0) — 'every seed' is that seed]"),
)
BEATS = (
    ("SmolVLA: a on s (real weights), a on u (real weights; one seed) beat both image controls on every seed "
     "(2 of 3 judged encoder-suite cells; 1 cannot be judged for missing rows)."),
    ("pi0.5: no encoder beats both image controls on every seed (0 of 1 judged encoder-suite cells; 1 cannot be "
     "judged for missing rows)."),
)


@pytest.fixture(scope="module")
def md(tmp_path_factory) -> str:
    return report.write_report(findings_table(), tmp_path_factory.mktemp("findings"), boot=QUICK).markdown.read_text()


def test_both_findings_lead_the_controls_section(md):
    section = md[md.index("## Controls"):md.index("### Each encoder's distance")]
    for line in (*READS, *BEATS):
        assert f"- {line}" in section
    assert "| SmolVLA | s | b | random-init | 1.5 (2) | 2.1 (2) | 1.45 (2) | beats zero-image only |  |" in section
    assert "| pi0.5 | s | a | real | 2.6 (2) | 2 (2) | 2.4 (2) | beats neither |  |" in section
    assert "1 encoder-suite cell with neither image control not shown." in section  # pi05/s/c: plain rows only


def test_sentences_are_in_backbone_order():
    a = analysis.analyze(findings_table(), boot=QUICK)
    assert report.reads_images_sentences(a)[0].startswith("SmolVLA · s") and report.beats_controls_sentences(a) == \
        list(BEATS)


def test_tables_without_native_or_image_controls_say_so(tmp_path):
    t = table(plain_rows({("smolvla", "s", "a"): [1.0, 1.1], ("pi05", "s", "a"): [1.0, 1.1]}))
    md = report.write_report(t, tmp_path, boot=QUICK).markdown.read_text()
    assert "No `native` or `zero-image` rows in the table: this cannot be judged." in md
    assert "No `zero-image` or `shuffled-image` rows in the table: this cannot be judged." in md


def test_no_judgeable_encoder_is_said_plainly():
    a = analysis.analyze(full_table(), boot=QUICK)
    assert ("pi0.5: no encoder-suite cell can be judged: all 10 lack plain-graft, zero-image or shuffled-image rows."
            in report.beats_controls_sentences(a))
