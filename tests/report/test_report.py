"""graftcache.report on the hand-built tables of tests/helpers/tables.py."""

from __future__ import annotations

import itertools
import re

import numpy as np
import polars as pl
import pytest
from helpers.tables import NEAR_TIE_MSE, full_table, minimal_table, plain_rows, table, write_results
from matplotlib.text import Text
from PIL import Image

from graftcache import analysis, report
from graftcache.cli import main
from graftcache.errors import GraftcacheError
from graftcache.report.random_init import random_init_warning
from graftcache.results import REPORT_COLUMNS

# fewer bootstrap replicates than the default, for speed
QUICK, MEDIUM, STEADY = (analysis.BootSettings(n_boot=n) for n in (100, 200, 500))

VERDICTS = (
    "On libero_spatial, the SmolVLA winner (siglip) is in pi0.5's top tier: the ranking transfers.",
    ("On libero_object, the SmolVLA winner (siglip) is not in pi0.5's top tier (dinov2-s): "
     "the ranking does not transfer."),
    ("On libero_10, the SmolVLA winners (dinov2-s, siglip) are in pi0.5's top tier: the ranking transfers. "
     "[pi0.5 top tier basis: exact ties only (single seed)]"),
    "On libero_goal, transfer cannot be judged (insufficient data): 1 encoder(s) on both backbones",
    # the other direction, and the counts (worked out in tests/helpers/tables.py)
    ("On libero_spatial, the pi0.5 winner (dinov2-s) is not in SmolVLA's top tier (siglip): "
     "the ranking does not transfer. Seed level: 1 of 3 cells transfer."),
    ("On libero_object, the pi0.5 winner (dinov2-s) is not in SmolVLA's top tier (siglip): "
     "the ranking does not transfer. Seed level: 0 of 3 cells transfer."),
    ("the ranking transfers in 3 of 6 comparisons (suite × direction) and 3 of 14 seed-level cells "
     "(suite × direction × seed)."),
)


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    out = tmp_path_factory.mktemp("report")
    paths = report.write_report(
        full_table(), out, commands={"sweep": "graftcache sweep cli/paper.toml"}, boot=STEADY
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
    assert "≥ 0.95 over 500 bootstrap replicates (seed 0)" in md  # the settings passed, not the defaults
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
    paths = report.write_report(full_table(random_init_for=("pi05", "resnet18")), tmp_path, boot=QUICK)
    md = paths.markdown.read_text()
    assert "> **Warning: random-init weights**" in md
    assert ("> - pi0.5 (`pi05`): backbone released (not random-init) weights; encoders with random-init weights: "
            "resnet18; real weights: dinov2-s, pi05-native, siglip") in md
    assert "SmolVLA (`smolvla`)" not in md  # no random-init weights in any of its rows
    assert md.index("random-init weights") < md.index("## Does the ranking transfer?")
    assert 'class="warning"' in paths.html.read_text()


DEMO_SHAPE = {("smolvla", "libero_spatial", e): [1.0, 1.1] for e in ("mobilenetv2", "timm:vit_tiny_patch16_224")}
DEMO_SHAPE |= {("pi05", "libero_spatial", e): [1.0, 1.1] for e in ("mobilenetv2", "timm:vit_tiny_patch16_224")}


def _banner(rows: list[dict]) -> tuple[str, ...]:
    (alert,) = random_init_warning(analysis.analyze(table(rows), boot=QUICK))
    return alert.lines


def test_the_banner_says_per_backbone_which_weights_were_random_init():
    """The demo's shape: tiny (train-tiny) backbones, a real-weights encoder beside a random-init one. Every row is
    random-init somewhere, but the banner must say the encoders' weights apart from the backbones'."""
    rows = [{**r, "backbone_random_init": True, "encoder_random_init": r["encoder"].startswith("timm:"),
             "random_init": True} for r in plain_rows(DEMO_SHAPE)]
    lead, *lines = _banner(rows)
    assert lead.startswith("8 of 8 rows were produced with random-init weights in the encoder or the backbone.")
    assert lines == [f"{label} (`{b}`): backbone random-init or train-tiny weights (all 4 rows); encoders with "
                     "random-init weights: timm:vit_tiny_patch16_224; real weights: mobilenetv2"
                     for label, b in (("SmolVLA", "smolvla"), ("pi0.5", "pi05"))]  # ladder order: smaller first


def test_the_banner_lists_a_native_tower_with_its_backbone_s_weights_not_as_random_init():
    """A tiny policy's own tower: its rows' encoder_random_init is true (results.schema) whether train-tiny trained
    it or not, so the banner says whose weights it has rather than calling them random-init."""
    shape = {("smolvla", "libero_spatial", e): [1.0, 1.1] for e in ("mobilenetv2", "smolvla-native")}
    rows = [{**r, "backbone_random_init": True, "encoder_random_init": r["encoder"] == "smolvla-native",
             "random_init": True} for r in plain_rows(shape)]
    _, *lines = _banner(rows)
    assert lines == ["SmolVLA (`smolvla`): backbone random-init or train-tiny weights (all 4 rows); the policy's own "
                     "tower, with the backbone's weights: smolvla-native; real weights: mobilenetv2"]


def test_the_banner_falls_back_to_random_init_where_rows_do_not_record_the_two_apart():
    """A table from before the split (or another tool): only random_init, said as such and never guessed apart;
    rows that record the split beside them are still said apart."""
    old = [{**r, "backbone_random_init": None, "encoder_random_init": None, "random_init": r["backbone"] == "pi05"}
           for r in plain_rows(DEMO_SHAPE)]
    old[0] |= {"backbone_random_init": True, "encoder_random_init": False, "random_init": True}  # smolvla's first
    lead, *lines = _banner(old)
    assert lead.startswith("5 of 8 rows were produced")
    assert lines == [
        "SmolVLA (`smolvla`): backbone random-init or train-tiny weights (1 of 4 rows); real weights: mobilenetv2",
        ("pi0.5 (`pi05`): encoder and backbone not recorded apart (only random_init), random-init in one or both: "
         "mobilenetv2, timm:vit_tiny_patch16_224 (4 rows)"),
    ]
    assert random_init_warning(analysis.analyze(table(plain_rows(DEMO_SHAPE)), boot=QUICK)) == []


def test_one_backbone_says_transfer_needs_two(tmp_path):
    small_only = full_table().filter(pl.col("backbone") == "smolvla")
    paths = report.write_report(small_only, tmp_path, boot=QUICK)
    md = paths.markdown.read_text()
    assert "The transfer question needs at least two backbones with valid plain-graft rows; present: SmolVLA" in md
    assert "ranking transfers" not in md and "Seed-level agreement" not in md
    assert paths.transfer.read_text() == ",".join(report.TRANSFER_CSV_COLUMNS) + "\n"  # no pair, no verdict
    assert sorted(p.name for p in paths.figures) == ["controls.png", "mse.png"]


def test_rerun_removes_stale_figures(tmp_path):
    report.write_report(full_table(), tmp_path, boot=QUICK)
    assert (tmp_path / "rank_transfer.png").exists()
    report.write_report(full_table().filter(pl.col("backbone") == "pi05"), tmp_path, boot=QUICK)
    assert not (tmp_path / "rank_transfer.png").exists() and not (tmp_path / "controls.png").exists()


def test_empty_table_still_reports(tmp_path):
    paths = report.write_report(full_table().head(0), tmp_path)
    md = paths.markdown.read_text()
    assert "No plain-graft rows" in md and "needs at least two backbones" in md and paths.figures == ()


def test_report_command_reads_a_file(tmp_path, capsys):
    results = write_results(tmp_path / "results.parquet")
    assert report.report_command(results, tmp_path / "out", command="graftcache report r.parquet out") == 0
    md = (tmp_path / "out" / "report.md").read_text()
    assert "- report: `graftcache report r.parquet out`" in md and f"Results: `{results}`" in md
    assert str(tmp_path / "out" / "report.html") in capsys.readouterr().out
    with pytest.raises(GraftcacheError, match="no results file"):
        report.report_command(tmp_path / "absent.parquet", tmp_path / "out")


def test_transfer_table_states_seed_level_counts(written):
    _, md, _ = written
    assert ("| libero_spatial | SmolVLA → pi0.5 | siglip | dinov2-s, siglip | 3 | 1 of 3 | 0.33 | 2 of 3 | "
            "transfers |  |") in md
    assert ("| libero_10 | pi0.5 → SmolVLA | dinov2-s, siglip | dinov2-s, siglip | 3 | "
            "0 of 1 (2 insufficient data) |") in md
    assert ("| libero_10 | 1 | SmolVLA → pi0.5 | — | — | insufficient data | — | "
            "seed 1 not run on pi0.5 |") in md


def test_near_tie_band_is_reported_as_such(tmp_path):
    md = report.write_report(table(plain_rows(NEAR_TIE_MSE)), tmp_path, boot=STEADY).markdown.read_text()
    assert ("On s, every shared encoder is in pi0.5's top tier (b, a): a seed-sensitive near-tie band, "
            "so the SmolVLA winner (a) landing in it is not a transfer.") in md
    assert "the ranking transfers." not in md and "| near-tie band |" in md
    assert "Other verdicts — near-tie band (not a transfer): 1 comparison, 0 cells; does not transfer:" in md


def test_minimal_schema_file_reports_with_a_seed_level_bootstrap(tmp_path, capsys):
    path = tmp_path / "paper.parquet"
    foreign = pl.lit("Table 2").alias("source")  # a column graftcache does not know
    minimal_table(NEAR_TIE_MSE).with_columns(foreign).write_parquet(path)
    assert report.report_command(path, tmp_path / "out") == 0
    assert "note: pi05: no row records backbone_params" in capsys.readouterr().err
    md = (tmp_path / "out" / "report.md").read_text()
    assert "- Per-episode MSEs: none (seed-level bootstrap, see Method)." in md
    assert "- Seed-level bootstrap: no row carries per-episode MSEs (`eval_mse_episodes`)" in md
    assert ("Columns without values (absent or all null): run_id, policy_id, format_version, backbone_params, "
            "policy,") in md
    # a table from before backbone_params: ordered by the released sizes, and the report says so
    assert ("- Backbone order: smolvla: no row records backbone_params (a table from before the column); ordered "
            "by the released size, 450M (its BackboneSpec's released_params).") in md
    assert "| SmolVLA | s | a | 1 | 1.1 ± 0.1 | 3 |" in md and "| seeds |" in md


@pytest.mark.parametrize("column", REPORT_COLUMNS)
def test_table_lacking_a_needed_column_is_one_named_error(tmp_path, column):
    path = tmp_path / "old.parquet"
    full_table().drop(column).write_parquet(path)
    with pytest.raises(GraftcacheError) as err:
        report.report_command(path, tmp_path / "out")
    assert str(err.value).startswith(f"{path}: results table lacks column(s) {column} (a report needs")
    assert "\n" not in str(err.value) and not (tmp_path / "out" / "report.md").exists()


def test_table_with_every_column_but_the_optional_ones_reports(tmp_path):
    older = full_table().drop("eval_mse_episodes", "n_eval_episodes", "command")
    path = write_results(tmp_path / "old.parquet", older)
    assert report.report_command(path, tmp_path / "out") == 0
    # in results.SCHEMA's order, where the declared setting columns (command among them) follow objective
    assert ("- Columns without values (absent or all null): command, eval_mse_episodes, eval_ci_mse, "
            "eval_ci_mse_episodes, n_eval_episodes.\n") in (
        tmp_path / "out" / "report.md"
    ).read_text()


@pytest.mark.parametrize(
    ("content", "says"),
    [
        (b"", "not a Parquet results table (empty file)"),
        (b"backbone,suite\nsmolvla,libero_spatial\n", "not a Parquet results table (parquet:"),
        (None, "no rows"),
    ],
    ids=["empty", "csv", "zero-rows"],
)
def test_unusable_file_is_one_line_naming_it(tmp_path, capsys, content, says):
    path = tmp_path / "results.parquet"
    if content is None:
        full_table().head(0).write_parquet(path)
    else:
        path.write_bytes(content)
    assert main(["report", str(path), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith(f"graftcache report: error: {path}: {says}"), err
    assert not (tmp_path / "out" / "report.md").exists()


CLOSE_MSE = {  # means 0.72 and 0.76 (and 0.74): bars from zero make them look equal
    (b, s, e): [m - 0.004, m, m + 0.004]
    for b in ("smolvla", "pi05")
    for s in ("libero_spatial", "libero_object")
    for e, m in (("timm:vit_tiny_patch16_224", 0.72), ("efficientnet-lite0", 0.74), ("mobilenetv2", 0.76))
}


def test_mse_axis_starts_near_the_data_not_at_zero(tmp_path):
    fig = report.figure_mse(analysis.analyze(table(plain_rows(CLOSE_MSE)), boot=MEDIUM))
    fig.savefig(tmp_path / "mse.png")
    _assert_real_png(tmp_path / "mse.png")
    panels = [ax for ax in fig.axes if ax.get_visible()]
    assert len(panels) == 4
    for ax in panels:
        lo, hi = ax.get_xlim()
        assert 0.6 < lo < 0.716 and 0.764 < hi < 0.9, (lo, hi)  # every seed inside, zero far outside
        assert (0.76 - 0.72) / (hi - lo) > 0.5  # the spread between encoders fills most of the axis


def _overlapping_texts(fig) -> list[tuple[str, str]]:
    """Pairs of drawn texts (tick labels, annotations, titles) whose boxes intersect on the canvas."""
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    texts = []
    for ax in fig.axes:
        ticks = [t for axis in (ax.xaxis, ax.yaxis) if axis.get_visible() for t in axis.get_ticklabels()]
        for t in [*ticks, *ax.texts, ax.title]:
            if isinstance(t, Text) and t.get_visible() and t.get_text().strip():
                texts.append((t.get_text(), t.get_window_extent(renderer)))
    return [(a, b) for (a, ba), (b, bb) in itertools.combinations(texts, 2) if ba.overlaps(bb)]


def test_rank_transfer_names_do_not_overprint_rank_labels():
    fig = report.figure_rank_transfer(analysis.analyze(table(plain_rows(CLOSE_MSE)), boot=MEDIUM))
    assert _overlapping_texts(fig) == []
    labels = [t.get_text() for ax in fig.axes for t in ax.get_yticklabels()]
    assert "timm:vit_tiny_patch16_224  1" in labels and "1  timm:vit_tiny_patch16_224" in labels
