"""graftcache.analysis on hand-built tables whose answers are worked out in tests/helpers/tables.py."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import polars as pl
import pytest
from helpers.tables import (
    BOTH_WAYS_MSE,
    NEAR_TIE_MSE,
    PLAIN_MSE,
    exact_p_greater,
    full_table,
    minimal_table,
    plain_rows,
    row,
    table,
)

from graftcache import analysis as A
from graftcache.errors import GraftcacheError
from graftcache.results import REPORT_COLUMNS, SCHEMA

# fewer bootstrap replicates than the default, for speed
MEDIUM, STEADY = A.BootSettings(n_boot=200), A.BootSettings(n_boot=500)


@pytest.fixture(scope="module")
def results() -> pl.DataFrame:
    return full_table()


def _one(frame: pl.DataFrame, **where) -> dict:
    hit = frame.filter(*(pl.col(k) == v for k, v in where.items()))
    assert len(hit) == 1, (where, hit)
    return hit.row(0, named=True)


def test_seed_summary_statistics_and_missing_cells(results):
    s = A.seed_summary(results)
    r = _one(s, backbone="smolvla", suite="libero_spatial", encoder="siglip")
    assert r["n"] == 3 and r["status"] == "ok" and r["seeds"] == [0, 1, 2]
    assert r["mean"] == pytest.approx(1.1) and r["std"] == pytest.approx(0.1)
    assert (r["min"], r["max"]) == (1.0, 1.2)
    # an encoder run on smolvla only is an explicit missing row on pi05, not an absent one
    gone = _one(s, backbone="pi05", suite="libero_goal", encoder="siglip")
    assert gone["status"] == "missing" and gone["n"] == 0 and gone["mean"] is None
    single = _one(s, backbone="pi05", suite="libero_10", encoder="resnet18")
    assert single["status"] == "single seed" and single["std"] is None
    # 2 backbones x 12 (suite, encoder) pairs; controls are not plain-graft cells
    assert len(s) == 24 and "smolvla-native" not in s["encoder"].to_list()


def test_invalid_mse_is_counted_not_averaged():
    t = table(
        plain_rows({("smolvla", "s", "a"): [1.0, 2.0]})
        + [row("smolvla", "s", "a", 2, float("nan")), row("smolvla", "s", "a", 3, None)]
    )
    r = _one(A.seed_summary(t), encoder="a")
    assert (r["n"], r["n_rows"], r["n_invalid"], r["mean"]) == (2, 4, 2, 1.5)
    problems = A.missing_cells(t)["problem"].to_list()
    assert problems == ["2 row(s) with null or non-finite eval_mse"]


def test_rankings_ties_share_the_lowest_rank(results):
    r = A.rankings(results).filter(pl.col("suite") == "libero_10", pl.col("backbone") == "smolvla")
    assert dict(zip(r["encoder"], r["rank"])) == {"dinov2-s": 1, "siglip": 1, "resnet18": 3}
    missing = _one(A.rankings(results), backbone="pi05", suite="libero_goal", encoder="siglip")
    assert missing["rank"] is None
    assert (
        _one(A.rankings(results), backbone="pi05", suite="libero_goal", encoder="dinov2-s")["n_ranked"] == 1
    )


def test_near_tie_band(results):
    band = A.near_tie_band(results)
    spatial = band.filter(pl.col("backbone") == "pi05", pl.col("suite") == "libero_spatial")
    assert set(spatial["best"]) == {"dinov2-s"}
    tier = dict(zip(spatial["encoder"], spatial["in_band"]))
    assert tier == {"dinov2-s": True, "siglip": True, "resnet18": False}
    p = dict(zip(spatial["encoder"], spatial["p_worse"]))
    assert p["dinov2-s"] is None and 0.3 < p["siglip"] < 0.95 and p["resnet18"] == 1.0
    assert set(spatial["basis"]) == {"seeds"}
    # every siglip seed above every dinov2-s seed: separable with certainty
    obj = _one(band, backbone="pi05", suite="libero_object", encoder="siglip")
    assert (obj["p_worse"], obj["in_band"]) == (1.0, False)


def test_single_seed_band_is_exact_ties_and_flagged(results):
    ten = A.near_tie_band(results).filter(pl.col("backbone") == "pi05", pl.col("suite") == "libero_10")
    assert dict(zip(ten["encoder"], ten["in_band"])) == {"dinov2-s": True, "siglip": True, "resnet18": False}
    assert set(ten["basis"]) == {"exact ties only (single seed)"}
    assert set(ten["best"]) == {"dinov2-s"}  # alphabetical first among the tied best


def test_band_missing_cell_is_null_not_dropped(results):
    r = _one(A.near_tie_band(results), backbone="pi05", suite="libero_goal", encoder="resnet18")
    assert r["in_band"] is None and r["basis"] == "missing"


def test_band_is_deterministic_and_seeded():
    # overlapping seeds, so p_worse is a genuine Monte-Carlo estimate
    t = table(plain_rows({("smolvla", "s", "a"): [1.0, 1.3, 1.6], ("smolvla", "s", "b"): [1.1, 1.5, 1.9]}))
    p = [
        A.near_tie_band(t, boot=replace(STEADY, seed=s)).filter(pl.col("encoder") == "b")["p_worse"][0]
        for s in (0, 0, 1)
    ]
    assert p[0] == p[1] and p[0] != p[2]
    # row order does not matter
    shuffled = t.sample(fraction=1.0, shuffle=True, seed=3)
    assert A.near_tie_band(shuffled, boot=STEADY).filter(pl.col("encoder") == "b")["p_worse"][0] == p[0]


def test_boot_settings_are_checked_and_carried():
    assert A.analyze(table(plain_rows(NEAR_TIE_MSE)), boot=MEDIUM).boot == A.BootSettings(0.95, 200, 0)
    for field, bad, rule in (("confidence", 1.0, "between 0 and 1"), ("n_boot", 0, "> 0"), ("seed", -1, ">= 0")):
        with pytest.raises(GraftcacheError, match=f"^{field} = {bad!r} must be {rule}"):
            A.BootSettings(**{field: bad})


def test_band_bootstraps_episodes_when_rows_carry_them():
    # one seed each: without episodes b (1.1 > 1.0) is out; its episodes overlap a's, so with them it is in
    t = table([row("smolvla", "s", "a", 0, 1.0), row("smolvla", "s", "b", 0, 1.1)]).with_columns(
        pl.Series(A.EPISODE_COLUMN, [[1.0, 1.4, 0.6, 1.0], [1.1, 0.7, 1.5, 1.1]], dtype=pl.List(pl.Float64))
    )
    with_ep = _one(A.near_tie_band(t), encoder="b")
    assert with_ep["in_band"] is True and with_ep["basis"] == "episodes (single seed)"
    without = _one(A.near_tie_band(t.with_columns(pl.lit(None, dtype=pl.List(pl.Float64)).alias(A.EPISODE_COLUMN))),
                   encoder="b")
    assert without["in_band"] is False and without["basis"] == "exact ties only (single seed)"


def test_transfer_verdicts(results):
    v = A.transfer_verdicts(results)
    suites = ["libero_10", "libero_goal", "libero_object", "libero_spatial"]
    assert v["suite"].to_list() == [s for s in suites for _ in range(2)]  # both directions
    assert v["source"].to_list() == ["smolvla", "pi05"] * 4  # small -> large first
    assert v["target"].to_list() == ["pi05", "smolvla"] * 4
    spatial = _one(v, suite="libero_spatial", source="smolvla")
    assert spatial["source_winner"] == "siglip" and spatial["target_winner"] == "dinov2-s"
    assert spatial["target_band"] == ["dinov2-s", "siglip"] and spatial["verdict"] == A.TRANSFERS
    assert spatial["basis"] == "seeds" and spatial["note"] is None
    back = _one(v, suite="libero_spatial", source="pi05")
    assert (back["source_winner"], back["target_band"], back["verdict"]) == (
        "dinov2-s", ["siglip"], A.DOES_NOT_TRANSFER
    )
    obj = _one(v, suite="libero_object", source="smolvla")
    assert obj["verdict"] == A.DOES_NOT_TRANSFER and obj["target_band"] == ["dinov2-s"]
    assert _one(v, suite="libero_object", source="pi05")["verdict"] == A.DOES_NOT_TRANSFER
    for source in ("smolvla", "pi05"):
        goal = _one(v, suite="libero_goal", source=source)
        assert goal["verdict"] == A.INSUFFICIENT and goal["n_common"] == 1 and goal["source_winner"] is None
        assert "resnet18 (only SmolVLA)" in goal["note"] and "siglip (only SmolVLA)" in goal["note"]
    ten = _one(v, suite="libero_10", source="smolvla")
    assert ten["source_winner"] == "dinov2-s, siglip" and ten["verdict"] == A.TRANSFERS
    assert ten["basis"] == "exact ties only (single seed)"
    ten_back = _one(v, suite="libero_10", source="pi05")
    assert ten_back["source_winner"] == "dinov2-s, siglip" and ten_back["verdict"] == A.TRANSFERS
    assert ten_back["target_band"] == ["dinov2-s", "siglip"] and ten_back["basis"] == "seeds"


def test_transfer_left_out_encoder_is_named_and_excluded():
    cells = {k: v for k, v in PLAIN_MSE.items() if k[1] == "libero_spatial"}
    cells[("pi05", "libero_spatial", "vit-b")] = [0.1, 0.1, 0.1]  # would be best on pi05, absent on smolvla
    v = _one(A.transfer_verdicts(table(plain_rows(cells))), suite="libero_spatial", source="smolvla")
    assert (
        v["verdict"] == A.TRANSFERS and "vit-b (only pi0.5)" in v["note"] and "vit-b" not in v["target_band"]
    )


def test_both_directions_are_judged_and_counted():
    # the design assumptions of BOTH_WAYS_MSE, checked by enumerating the bootstrap (not by graftcache)
    m = BOTH_WAYS_MSE
    assert exact_p_greater(m[("pi05", "s1", "a")], m[("pi05", "s1", "b")]) < 0.8
    assert exact_p_greater(m[("smolvla", "s2", "b")], m[("smolvla", "s2", "a")]) < 0.8
    assert exact_p_greater(m[("smolvla", "s1", "b")], m[("smolvla", "s1", "a")]) == 1.0
    assert exact_p_greater(m[("pi05", "s2", "a")], m[("pi05", "s2", "b")]) == 1.0
    t = table(plain_rows(BOTH_WAYS_MSE))
    v = {(r["suite"], r["source"]): r["verdict"] for r in A.transfer_verdicts(t).iter_rows(named=True)}
    assert v == {
        ("s1", "smolvla"): A.TRANSFERS,
        ("s1", "pi05"): A.DOES_NOT_TRANSFER,
        ("s2", "smolvla"): A.DOES_NOT_TRANSFER,
        ("s2", "pi05"): A.TRANSFERS,
    }
    cells = A.seed_verdicts(t)
    assert len(cells) == 12  # 2 suites x 3 seeds x 2 directions
    transferring = cells.filter(pl.col("verdict") == A.TRANSFERS).select("suite", "seed", "source").rows()
    assert sorted(transferring) == [("s1", 0, "pi05"), ("s1", 0, "smolvla")]
    assert set(cells["basis"]) == {"exact ties only (single seed)"}
    overall = A.verdict_counts(A.transfer_verdicts(t)).row(0, named=True)
    assert (overall["n_transfers"], overall["n_judged"], overall["n_does_not_transfer"]) == (2, 4, 2)
    seed_level = A.verdict_counts(cells).row(0, named=True)
    assert (seed_level["n_transfers"], seed_level["n_judged"], seed_level["n_insufficient"]) == (2, 12, 0)
    per = {(r["suite"], r["source"]): (r["n_transfers"], r["n_judged"])
           for r in A.verdict_counts(cells, ("suite", "source")).iter_rows(named=True)}
    assert per == {("s1", "smolvla"): (1, 3), ("s1", "pi05"): (1, 3), ("s2", "smolvla"): (0, 3),
                   ("s2", "pi05"): (0, 3)}


def test_fixture_counts_with_insufficient_cells(results):
    c = A.verdict_counts(A.transfer_verdicts(results)).row(0, named=True)
    assert (c["n_transfers"], c["n_judged"], c["n_insufficient"]) == (3, 6, 2)
    cells = A.seed_verdicts(results)
    s = A.verdict_counts(cells).row(0, named=True)
    assert (s["n_transfers"], s["n_judged"], s["n_insufficient"]) == (3, 14, 10)
    assert _one(cells, suite="libero_10", seed=1, source="smolvla")["note"] == "seed 1 not run on pi0.5"


def test_a_tier_holding_every_encoder_is_a_near_tie_not_a_transfer():
    m = NEAR_TIE_MSE
    assert exact_p_greater(m[("pi05", "s", "a")], m[("pi05", "s", "b")]) < 0.8  # pi05 cannot separate a, b
    v = A.transfer_verdicts(table(plain_rows(NEAR_TIE_MSE)))
    forward = _one(v, source="smolvla")
    assert forward["verdict"] == A.NEAR_TIE != A.TRANSFERS and forward["target_band"] == ["b", "a"]
    assert _one(v, source="pi05")["verdict"] == A.DOES_NOT_TRANSFER
    assert A.NEAR_TIE in A.VERDICTS and len(set(A.VERDICTS)) == 4
    assert A.verdict_counts(v).row(0, named=True)["n_near_tie"] == 1


def test_minimal_table_is_analysed_with_a_seed_level_bootstrap():
    minimal = minimal_table(BOTH_WAYS_MSE)
    assert minimal.columns == list(REPORT_COLUMNS)
    a = A.analyze(minimal, boot=STEADY)
    assert set(a.results.columns) == set(SCHEMA) and a.results["command"].null_count() == len(minimal)
    assert a.episode_coverage == (0, 12)
    assert set(a.band["basis"]) == {"seeds"}
    full = A.analyze(table(plain_rows(BOTH_WAYS_MSE)), boot=STEADY)
    assert a.verdicts.equals(full.verdicts) and a.seed_verdicts.equals(full.seed_verdicts)


def test_episode_coverage_counts_cells_with_episodes():
    t = table([row("smolvla", "s", "a", 0, 1.0), row("smolvla", "s", "b", 0, 1.1)]).with_columns(
        pl.Series(A.EPISODE_COLUMN, [[1.0, 1.0], None], dtype=pl.List(pl.Float64))
    )
    assert A.episode_coverage(t) == (1, 2)


def test_one_backbone_has_no_pair_to_judge(results):
    # with one backbone there is no pair: no verdict, pairing or tau row, and the ladder says why
    small_only = results.filter(pl.col("backbone") == "smolvla")
    a = A.analyze(small_only, boot=MEDIUM)
    assert a.transfer_gap == "needs at least two backbones with valid plain-graft rows; present: SmolVLA"
    for frame in (a.verdicts, a.seed_verdicts, a.pairings, a.disagreements, a.tau, a.headline):
        assert len(frame) == 0
    assert len(a.band) == 12 and a.backbones == ["smolvla"]


def test_seed_pairings_and_counts(results):
    pairs = A.seed_pairings(results)
    spatial = pairs.filter(pl.col("suite") == "libero_spatial").sort("seed")
    assert spatial["disagree"].to_list() == [False, True, True]
    assert spatial["large_top1"].to_list() == ["siglip", "dinov2-s", "dinov2-s"]
    ten = pairs.filter(pl.col("suite") == "libero_10").sort("seed")
    assert ten["disagree"].to_list() == [False, None, None]  # seed 0: tie {dinov2-s, siglip} shares siglip
    assert ten["note"][1] == "seed 1 not run on pi0.5"
    counts = {r["suite"]: r for r in A.seed_disagreement_counts(results).iter_rows(named=True)}
    assert (counts["libero_spatial"]["n_disagree"], counts["libero_spatial"]["n_pairings"]) == (2, 3)
    assert counts["libero_object"]["fraction_disagree"] == 1.0
    assert (counts["libero_goal"]["n_pairings"], counts["libero_goal"]["n_unpaired"]) == (0, 3)
    assert counts["libero_goal"]["fraction_disagree"] is None


def test_tau_b_against_hand_values_and_scipy():
    assert A.tau_b([1, 2, 3], [2, 1, 3]) == pytest.approx(1 / 3)
    assert A.tau_b([2, 2, 4], [1, 1, 2]) == pytest.approx(1.0)
    assert A.tau_b([1, 1, 1], [1, 2, 3]) is None and A.tau_b([1], [1]) is None
    stats = pytest.importorskip("scipy.stats")
    rng = np.random.default_rng(0)
    for _ in range(20):
        x, y = rng.integers(0, 4, 8), rng.integers(0, 4, 8)
        want = stats.kendalltau(x, y, variant="b").statistic
        got = A.tau_b(x, y)
        assert (got is None and math.isnan(want)) or got == pytest.approx(want)


def test_kendall_tau_per_suite(results):
    tau = {r["suite"]: r for r in A.kendall_tau(results).iter_rows(named=True)}
    assert tau["libero_spatial"]["tau_b"] == pytest.approx(1 / 3)
    assert tau["libero_object"]["tau_b"] == pytest.approx(-1 / 3)
    assert tau["libero_10"]["tau_b"] == pytest.approx(1.0)
    assert tau["libero_goal"]["tau_b"] is None and "fewer than two" in tau["libero_goal"]["note"]


def test_wrapper_non_neutrality(results):
    w = A.wrapper_non_neutrality(results)
    small = _one(w, backbone="smolvla")
    assert small["non_neutrality"] == pytest.approx(0.2) and small[
        "non_neutrality_seed_std"
    ] == pytest.approx(0.1)
    assert small["native_encoder"] == "smolvla-native" and (small["native_n"], small["native_graft_n"]) == (
        1,
        3,
    )
    large = _one(w, backbone="pi05")
    assert large["non_neutrality"] is None and large["note"] == "no valid native-graft rows"
    assert len(A.wrapper_non_neutrality(results, by_suite=False)) == 2


def test_controls_distance(results):
    c = A.controls_distance(results)
    sig = _one(c, backbone="smolvla", suite="libero_spatial", encoder="siglip", control="zero-image")
    assert sig["distance"] == pytest.approx((3.1 - 1.1) / 3.1) and sig["within_noise"] is False
    shuf = _one(c, backbone="smolvla", suite="libero_spatial", encoder="siglip", control="shuffled-image")
    assert shuf["distance"] == pytest.approx((2.2 - 1.1) / 2.2)
    res = _one(c, backbone="smolvla", suite="libero_spatial", encoder="resnet18", control="zero-image")
    assert res["distance"] == pytest.approx((3.05 - 3.1) / 3.05) and res["within_noise"] is True
    gap = _one(c, backbone="smolvla", suite="libero_spatial", encoder="dinov2-s", control="zero-image")
    assert (
        gap["distance"] is None and gap["within_noise"] is None and gap["note"] == "no valid zero-image rows"
    )
    # controls=None picks up every encoder-level control in the table, never the native ones
    assert set(A.controls_distance(results, controls=None)["control"]) == {"zero-image", "shuffled-image"}


def test_control_rows_without_plain_rows_are_reported():
    t = table(
        plain_rows({("smolvla", "s", "a"): [1.0]})
        + [row("smolvla", "s", "zero", 0, 2.0, control="zero-image")]
    )
    r = _one(A.controls_distance(t, controls=["zero-image"]), encoder="zero")
    assert r["enc_mse"] is None and r["note"] == "no valid plain-graft rows for this encoder"


def test_missing_cells_lists_every_gap(results):
    m = A.missing_cells(results)
    assert set(m.filter(pl.col("backbone") == "pi05", pl.col("suite") == "libero_goal")["encoder"]) == {
        "siglip",
        "resnet18",
    }
    assert len(m) == 2  # pi05/libero_10 ran seed 0 only for every encoder: nothing lacks a seed there
    t = table(plain_rows({("smolvla", "s", "a"): [1.0, 1.1, 1.2], ("smolvla", "s", "b"): [1.0, 1.1]}))
    assert A.missing_cells(t).row(0, named=True)["problem"] == "missing seed(s) 2"


def test_analyze_bundles_and_rejects_mixed_recipes(results):
    a = A.analyze(results, boot=MEDIUM)
    assert a.backbones == ["smolvla", "pi05"] and len(a.suites) == 4
    assert len(a.verdicts) == 8 and set(a.controls["control"]) == {"zero-image", "shuffled-image"}
    assert len(a.seed_verdicts) == 24  # 4 suites x 3 seeds x 2 directions
    mixed = pl.concat(
        [results, table([row("smolvla", "libero_spatial", "siglip", 0, 9.0, objective="align")])]
    )
    with pytest.raises(GraftcacheError, match="differing in objective"):
        A.analyze(mixed)


def test_empty_and_malformed_tables():
    empty = table([])
    a = A.analyze(empty)
    assert len(a.band) == 0 and len(a.verdicts) == 0 and len(a.controls) == 0
    with pytest.raises(GraftcacheError, match="eval_mse"):
        A.seed_summary(empty.drop("eval_mse"))
