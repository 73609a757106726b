"""graftcache.analysis.findings on the hand-built table of tests/helpers/findings.py (answers worked out there)."""

from __future__ import annotations

import polars as pl
import pytest
from helpers.findings import findings_table
from helpers.tables import minimal_table, table

from graftcache import analysis as A

ONE_SEED = "one seed: native (seed 0), zero-image (seed 0) — 'every seed' is that seed"


@pytest.fixture(scope="module")
def results() -> pl.DataFrame:
    return findings_table()


def _one(frame: pl.DataFrame, **where) -> dict:
    hit = frame.filter(*(pl.col(k) == v for k, v in where.items()))
    assert len(hit) == 1, (where, hit)
    return hit.row(0, named=True)


def test_native_separated_from_pooled_zero_image(results):
    r = _one(A.native_vs_zero_image(results), backbone="smolvla", suite="s")
    assert r["verdict"] == A.SEPARATED and r["note"] is None
    assert (r["native_mean"], r["native_max"]) == pytest.approx((1.05, 1.1))
    assert (r["zero_n"], r["zero_mean"], r["zero_min"], r["zero_encoders"]) == (4, pytest.approx(2.15), 2.0, "a, b")
    assert r["gap"] == pytest.approx((2.15 - 1.05) / 2.15)


def test_one_overlapping_seed_is_not_separated(results):
    r = _one(A.native_vs_zero_image(results), backbone="pi05", suite="s")
    assert r["verdict"] == A.NOT_SEPARATED and r["gap"] == pytest.approx((2.5 - 1.55) / 2.5)


def test_missing_sides_give_a_note_never_a_verdict(results):
    reads = A.native_vs_zero_image(results)
    for backbone, suite, note in (("pi05", "t", "no valid zero-image rows"), ("smolvla", "t", "no valid native rows")):
        r = _one(reads, backbone=backbone, suite=suite)
        assert r["verdict"] is None and r["gap"] is None and r["note"] == note


def test_a_single_seed_is_judged_and_named(results):
    r = _one(A.native_vs_zero_image(results), backbone="smolvla", suite="u")
    assert r["verdict"] == A.SEPARATED and r["note"] == ONE_SEED


def test_per_encoder_detail(results):
    by = A.native_vs_zero_image(results, by_encoder=True)
    assert _one(by, backbone="smolvla", suite="s", encoder="b")["zero_min"] == 2.1
    assert _one(by, backbone="pi05", suite="s", encoder="a")["verdict"] == A.NOT_SEPARATED


def test_encoders_against_both_image_controls(results):
    b = A.beats_image_controls(results)
    win = _one(b, backbone="smolvla", suite="s", encoder="a")
    assert win["verdict"] == A.BEATS_BOTH and win["encoder_random_init"] is False
    half = _one(b, backbone="smolvla", suite="s", encoder="b")  # 1.5 < zero 2.1, but not < shuffled 1.45
    assert (half["beats_zero"], half["beats_shuffled"], half["verdict"]) == (True, False, "beats zero-image only")
    assert half["encoder_random_init"] is True
    assert _one(b, backbone="pi05", suite="s", encoder="a")["verdict"] == "beats neither"
    single = _one(b, backbone="smolvla", suite="u", encoder="a")
    assert single["verdict"] == A.BEATS_BOTH and single["note"].startswith("one seed: plain-graft (seed 0)")


def test_encoders_missing_rows_get_notes(results):
    b = A.beats_image_controls(results)
    plain_only = _one(b, backbone="pi05", suite="s", encoder="c")
    assert plain_only["verdict"] is None and plain_only["encoder_random_init"] is None
    assert plain_only["note"] == "no valid zero-image rows; no valid shuffled-image rows"
    control_only = _one(b, backbone="smolvla", suite="t", encoder="a")
    assert control_only["verdict"] is None and control_only["beats_zero"] is None
    assert control_only["note"] == "no valid plain-graft rows; no valid shuffled-image rows"


def test_empty_and_minimal_tables_and_analyze(results):
    assert len(A.native_vs_zero_image(table([]))) == 0 and len(A.beats_image_controls(table([]))) == 0
    bare = A.beats_image_controls(minimal_table({("smolvla", "s", "a"): [1.0]}))  # no encoder_random_init column
    assert bare.select("encoder_random_init", "note").row(0) == (
        None, "no valid zero-image rows; no valid shuffled-image rows")
    a = A.analyze(results, boot=A.BootSettings(n_boot=50))
    assert len(a.reads_images) == 5 and len(a.beats_controls) == 6
