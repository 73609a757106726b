"""Any number of backbones: the ladder (ordered by backbone_params), verdicts for every pair, the headline, the
tau-b matrix, transfer.csv and the N-backbone report, on tests/helpers/tables.py's LADDER_MSE (answers worked
out there), plus the MSE / CI-MSE choice."""

from __future__ import annotations

import csv

import polars as pl
import pytest
from helpers.tables import LADDER_PARAMS, PLAIN_MSE, ladder_table, minimal_table, plain_rows, row, table

from graftcache import analysis as A
from graftcache import report
from graftcache.cli import main
from graftcache.errors import GraftcacheError

QUICK = A.BootSettings(n_boot=300)
T, N, D, X = A.TRANSFERS, A.NEAR_TIE, A.DOES_NOT_TRANSFER, A.INSUFFICIENT  # X: insufficient data

# (suite, source, target) -> (source winner, target top tier, verdict), pooled over seeds
POOLED = {
    ("s", "kilo", "alpha"): ("a", ["a"], T), ("s", "alpha", "kilo"): ("a", ["a"], T),
    ("s", "kilo", "mu"): ("a", ["c"], D), ("s", "mu", "kilo"): ("c", ["a"], D),
    ("s", "alpha", "mu"): ("a", ["c"], D), ("s", "mu", "alpha"): ("c", ["a"], D),
    ("t", "kilo", "alpha"): ("a", ["b", "a"], N), ("t", "alpha", "kilo"): ("b", ["a"], D),
    ("t", "kilo", "mu"): (None, [], X), ("t", "mu", "kilo"): (None, [], X),
    ("t", "alpha", "mu"): (None, [], X), ("t", "mu", "alpha"): (None, [], X),
}


def _seed_answer(suite: str, seed: int, source: str, target: str) -> tuple[str | None, list[str], str]:
    """Seed-level answers: suite s repeats the pooled verdicts; suite t as tests/helpers/tables.py works out."""
    if suite == "s" or POOLED[suite, source, target][2] == X:
        return POOLED[suite, source, target]
    if seed == 0:
        return "a", ["a"], T
    return ("a", ["b"], D) if source == "kilo" else ("b", ["a"], D)


@pytest.fixture(scope="module")
def ladder() -> A.Analysis:
    return A.analyze(ladder_table(), boot=QUICK)


def test_backbones_are_ordered_by_recorded_parameters_not_names(ladder):
    assert ladder.ladder.backbones == ("kilo", "alpha", "mu") and ladder.ladder.params == LADDER_PARAMS
    assert ladder.ladder.notes == () and (ladder.small, ladder.large) == ("kilo", "mu")
    assert ladder.ladder.pairs == [("kilo", "alpha"), ("kilo", "mu"), ("alpha", "mu")]


def test_every_pair_is_judged_both_ways(ladder):
    v = ladder.verdicts
    got = {(r["suite"], r["source"], r["target"]): (r["source_winner"], r["target_band"] or [], r["verdict"])
           for r in v.iter_rows(named=True)}
    assert got == POOLED and len(v) == 12
    assert v.select("source", "target").rows()[:2] == [("kilo", "alpha"), ("alpha", "kilo")]  # smaller first


def test_seed_level_cells_for_every_pair(ladder):
    cells = ladder.seed_verdicts
    assert len(cells) == 2 * 3 * 3 * 2  # suites x pairs x seeds x directions
    for r in cells.iter_rows(named=True):
        want = _seed_answer(r["suite"], r["seed"], r["source"], r["target"])
        assert (r["source_winner"], r["target_band"] or [], r["verdict"]) == want, r


def test_headline_transfers_one_rung_then_breaks(ladder):
    h = {r["suite"]: r for r in ladder.headline.iter_rows(named=True)}
    s = h["s"]
    assert (s["smallest"], s["largest"], s["smallest_winner"], s["largest_top_tier"]) == ("kilo", "mu", "a", ["c"])
    assert s["verdict"] == D and s["steps"] == [T, D] and s["break_at"] == "alpha -> mu" and s["open_rungs"] == 0
    t = h["t"]
    assert (t["verdict"], t["steps"], t["break_at"], t["open_rungs"]) == (X, [N, X], None, 1)
    said = report.headline_sentences(ladder)
    assert said[0] == (
        "On s, the smallest backbone's (kilo) winner (a) is not in the largest one's (mu) top tier (c): the ranking "
        "does not transfer from the bottom of the ladder to its top. Rung by rung (kilo → alpha: transfers; "
        "alpha → mu: does not transfer): the ranking breaks at alpha → mu.")
    assert said[1].endswith("Rung by rung (kilo → alpha: near-tie band; alpha → mu: insufficient data): the ranking "
                            "breaks at no rung that could be judged (1 rung could not be judged).")


def test_tau_b_matrix(ladder):
    m = A.tau_matrix(ladder.tau, "s", ladder.ladder.backbones)
    want = [[1.0, 1 / 3, -1.0], [1 / 3, 1.0, -1 / 3], [-1.0, -1 / 3, 1.0]]
    assert m == [[pytest.approx(x) for x in r] for r in want]
    t = A.tau_matrix(ladder.tau, "t", ladder.ladder.backbones)
    assert t[0][1] == pytest.approx(-1.0) and t[0][2] is None and t[1][2] is None  # mu shares one encoder


def test_transfer_csv_holds_every_verdict(tmp_path):
    paths = report.write_report(ladder_table(), tmp_path, boot=QUICK)
    assert paths.transfer == tmp_path / "transfer.csv"
    with open(paths.transfer, newline="") as f:
        rows = list(csv.reader(f))
    assert tuple(rows[0]) == report.TRANSFER_CSV_COLUMNS
    want = [[s, "", src, dst, w or "", ";".join(tier), v] for (s, src, dst), (w, tier, v) in POOLED.items()]
    for suite in ("s", "t"):
        for small, large in (("kilo", "alpha"), ("kilo", "mu"), ("alpha", "mu")):
            for seed in range(3):
                for src, dst in ((small, large), (large, small)):
                    w, tier, v = _seed_answer(suite, seed, src, dst)
                    want.append([suite, str(seed), src, dst, w or "", ";".join(tier), v])
    assert rows[1:] == want


def test_n_backbone_report_end_to_end(tmp_path):
    paths = report.write_report(ladder_table(), tmp_path, boot=QUICK)
    md = paths.markdown.read_text()
    assert sorted(p.name for p in paths.figures) == ["mse.png", "rank_bump.png"]  # no two-backbone slope chart
    assert "- Backbones, by parameter count: kilo (`kilo`, 500M), alpha (`alpha`, 2B), mu (`mu`, 7B)." in md
    assert "| 1 | kilo | 500M |" in md and "| 3 | mu | 7B |" in md
    assert "the ranking breaks at alpha → mu." in md
    assert ("both directions of every pair of the 3 backbones (6 directions), the ranking transfers in 2 of 8 "
            "comparisons (suite × direction) and 8 of 24 seed-level cells") in md
    assert "On t, transfer between mu and kilo cannot be judged (insufficient data)" not in md  # pairs say once
    assert "On t, transfer between alpha and kilo" not in md
    assert "On t, transfer between kilo and mu cannot be judged (insufficient data): 1 encoder(s) on both" in md
    assert "| τb | kilo | alpha | mu |" in md and "| kilo | 1.00 | 0.33 | -1.00 |" in md
    assert "| s | alpha → mu | a | c | 3 | 0 of 3 | -0.33 |" in md


def test_two_backbones_keep_the_papers_report(tmp_path):
    md = report.write_report(table(plain_rows(PLAIN_MSE)), tmp_path, boot=QUICK).markdown.read_text()
    assert "Rung by rung" not in md and "rank_bump.png" not in md and "| τb |" not in md
    assert "both directions (SmolVLA → pi0.5, pi0.5 → SmolVLA)" in md


def test_unorderable_backbones_are_named_errors():
    unknown = minimal_table({("kilo", "s", "a"): [1.0], ("smolvla", "s", "a"): [1.0]})
    with pytest.raises(GraftcacheError, match="^backbone kilo: no row records backbone_params and graftcache knows"):
        A.analyze(unknown)
    mixed = ladder_table().with_columns(
        backbone_params=pl.when(pl.col("seed") == 2).then(1).otherwise(pl.col("backbone_params")))
    with pytest.raises(GraftcacheError, match=r"^backbone alpha: its rows record 2 parameter counts \(1, 2000000000\)"):
        A.analyze(mixed)


# CI-MSE beside MSE: on b1, MSE ranks a < b and CI-MSE b < a; on b2 both rank a < b.
def _scored_table() -> pl.DataFrame:
    rows = []
    for b, params in (("b1", 10), ("b2", 20)):
        for e, mse, ci in (("a", 1.0, 4.0), ("b", 2.0, 3.0 if b == "b1" else 5.0)):
            for seed in range(2):
                rows.append(row(b, "s", e, seed, mse + seed / 100, backbone_params=params,
                                eval_ci_mse=ci + seed / 100, eval_ci_mse_episodes=[ci, None, ci + 0.02]))
    return table(rows)


def test_score_choice_ranks_by_ci_mse_and_shows_disagreement(tmp_path):
    t = _scored_table()
    by_mse, by_ci = A.analyze(t, boot=QUICK), A.analyze(t, score="ci-mse", boot=QUICK)
    top = {s: dict(a.band.filter(pl.col("rank") == 1).select("backbone", "encoder").iter_rows())
           for s, a in (("mse", by_mse), ("ci", by_ci))}
    assert top == {"mse": {"b1": "a", "b2": "a"}, "ci": {"b1": "b", "b2": "a"}}
    assert by_ci.results["eval_mse_episodes"][0].to_list() == [4.0, 4.02]  # the episode without CI left out
    d = {r["backbone"]: r for r in by_mse.scores.iter_rows(named=True)}
    assert (d["b1"]["mse_top1"], d["b1"]["ci_mse_top1"], d["b1"]["same_top1"]) == ("a", "b", False)
    assert d["b1"]["moved"] == ["a: 1 -> 2", "b: 2 -> 1"] and d["b1"]["tau_b"] == pytest.approx(-1.0)
    assert d["b2"]["same_top1"] is True and d["b2"]["moved"] == []
    path = tmp_path / "r.parquet"
    t.write_parquet(path)
    assert main(["report", str(path), "--out", str(tmp_path / "out"), "--score", "ci-mse"]) == 0
    assert (tmp_path / "out" / "transfer.csv").read_text().startswith(",".join(report.TRANSFER_CSV_COLUMNS))
    md = (tmp_path / "out" / "report.md").read_text()
    assert "- Score: critical-interval MSE (CI-MSE) (`--score ci-mse`)." in md
    assert "the top-1 encoder differs in 1 of 2 (backbone, suite) cells" in md
    assert "| b1 | s | a | b | no | 2 | -1.00 | a: 1 -> 2; b: 2 -> 1 |" in md


def test_ci_mse_without_values_is_a_one_line_error(tmp_path, capsys):
    path = tmp_path / "old.parquet"
    ladder_table().write_parquet(path)
    assert main(["report", str(path), "--out", str(tmp_path / "out"), "--score", "ci-mse"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "no plain-graft row carries eval_ci_mse" in err
    assert not (tmp_path / "out" / "report.md").exists()
