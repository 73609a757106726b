"""graftcache.report on the hand-built tables of tests/analysis_fixtures.py."""

from __future__ import annotations

import re

import numpy as np
import polars as pl
import pytest
from analysis_fixtures import full_table, write_results
from PIL import Image

from graftcache import report
from graftcache.errors import GraftcacheError

VERDICTS = (
    "On libero_spatial, the SmolVLA winner (siglip) is in pi0.5's top tier: the ranking transfers.",
    ("On libero_object, the SmolVLA winner (siglip) is not in pi0.5's top tier (dinov2-s): "
     "the ranking does not transfer."),
    ("On libero_10, the SmolVLA winners (dinov2-s, siglip) are in pi0.5's top tier: the ranking transfers. "
     "[pi0.5 top tier basis: exact ties only (single seed)]"),
    "On libero_goal, transfer cannot be judged (insufficient data): 1 encoder(s) on both backbones",
)


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    out = tmp_path_factory.mktemp("report")
    paths = report.write_report(
        full_table(), out, commands={"sweep": "graftcache sweep cli/paper.toml"}, n_boot=500
    )
    return paths, paths.markdown.read_text(), paths.html.read_text()


def _assert_real_png(path):
    with Image.open(path) as im:
        im.verify()
    pixels = np.asarray(Image.open(path).convert("RGB"))
    assert pixels.shape[0] > 150 and pixels.shape[1] > 300
    ink = (pixels < 200).any(axis=2).mean()  # share of non-background pixels
    assert 0.01 < ink < 0.9, (path, ink)
    packed = (pixels.astype(np.uint32) << np.array([16, 8, 0], dtype=np.uint32)).sum(axis=2)
    assert len(np.unique(packed)) > 20  # anti-aliased text, bars and dots, not a flat image


def test_files_and_figures(written):
    paths, md, _ = written
    assert paths.markdown.is_file() and paths.html.is_file()
    assert sorted(p.name for p in paths.figures) == ["controls.png", "mse.png", "rank_transfer.png"]
    for png in paths.figures:
        _assert_real_png(png)
        assert f"]({png.name})" in md  # referenced relatively from the markdown


def test_markdown_states_verdicts_proxy_and_provenance(written):
    _, md, _ = written
    for sentence in VERDICTS:
        assert sentence in md
    assert "validation MSE is a weak predictor of rollout success" in md
    assert "Warning: random-init" not in md
    assert "- sweep: `graftcache sweep cli/paper.toml`" in md
    # every row's command and cache key is cited
    for cmd in full_table()["command"]:
        assert f"`{cmd}`" in md
    assert "`key-siglip-libero_spatial`" in md
    assert "| SmolVLA | libero_spatial | smolvla-native | 1 (1) | 1.2 (3) | +20.0% |" in md
    assert "SmolVLA · libero_spatial · resnet18: the image features add nothing measurable" in md
    assert "| pi0.5 | libero_goal | siglip | no plain-graft rows |" in md


def test_html_is_self_contained_and_says_the_same(written):
    _, md, page = written
    assert page.count('src="data:image/png;base64,') == 3
    assert not re.search(r'src="(?!data:)', page)
    for sentence in VERDICTS:
        assert sentence.replace("&", "&amp;") in page
    assert page.count("<table>") == md.count("\n|---") and page.count("<h2>") == md.count("\n## ")


def test_random_init_rows_trigger_the_warning(tmp_path):
    paths = report.write_report(full_table(random_init_for=("pi05", "resnet18")), tmp_path, n_boot=100)
    md = paths.markdown.read_text()
    assert "> **Warning: random-init weights**" in md
    assert "> - pi0.5 (`pi05`): resnet18 (7 rows)" in md
    assert md.index("random-init weights") < md.index("## Does the ranking transfer?")
    assert 'class="warning"' in paths.html.read_text()


def test_one_backbone_says_transfer_needs_two(tmp_path):
    small_only = full_table().filter(pl.col("backbone") == "smolvla")
    paths = report.write_report(small_only, tmp_path, n_boot=100)
    md = paths.markdown.read_text()
    assert "The transfer question needs two backbones (SmolVLA and pi0.5); present: SmolVLA" in md
    assert "ranking transfers" not in md and "Seed-level agreement" not in md
    assert sorted(p.name for p in paths.figures) == ["controls.png", "mse.png"]


def test_rerun_removes_stale_figures(tmp_path):
    report.write_report(full_table(), tmp_path, n_boot=100)
    assert (tmp_path / "rank_transfer.png").exists()
    report.write_report(full_table().filter(pl.col("backbone") == "pi05"), tmp_path, n_boot=100)
    assert not (tmp_path / "rank_transfer.png").exists() and not (tmp_path / "controls.png").exists()


def test_empty_table_still_reports(tmp_path):
    paths = report.write_report(full_table().head(0), tmp_path)
    md = paths.markdown.read_text()
    assert "No plain-graft rows" in md and "needs two backbones" in md and paths.figures == ()


def test_report_command_reads_a_file(tmp_path, capsys):
    results = write_results(tmp_path / "results.parquet")
    assert report.report_command(results, tmp_path / "out", command="graftcache report r.parquet out") == 0
    md = (tmp_path / "out" / "report.md").read_text()
    assert "- report: `graftcache report r.parquet out`" in md and f"Results: `{results}`" in md
    assert str(tmp_path / "out" / "report.html") in capsys.readouterr().out
    with pytest.raises(GraftcacheError, match="no results file"):
        report.report_command(tmp_path / "absent.parquet", tmp_path / "out")
