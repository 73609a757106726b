"""The two findings a demo's report must show, each judged on every seed: does a backbone read its images (its own
tower, as loaded, against the zero-image control), and which encoders beat both image controls?

One side beats the other on every seed when its worst seed is below the other's best (max < min): no seed
overlaps, so the claim needs no bootstrap and holds for each seed that was run. A side without valid rows gives no
verdict, only a note; a side with one seed is named in the note, since its "every seed" is that one.
"""

from __future__ import annotations

from functools import reduce

import polars as pl

from graftcache.analysis.table import (
    CELL,
    GROUP,
    NATIVE_CONTROL,
    PLAIN,
    SHUFFLED_IMAGE,
    ZERO_IMAGE,
    check,
    control_rows,
)
from graftcache.results import conform

SEPARATED = "separated on every seed"
NOT_SEPARATED = "not separated"
BEATS_BOTH = "beats both on every seed"
#: (beats zero-image on every seed, beats shuffled-image on every seed) -> verdict
BEATS = {
    (True, True): BEATS_BOTH,
    (True, False): "beats zero-image only",
    (False, True): "beats shuffled-image only",
    (False, False): "beats neither",
}
#: the sides of each finding: column prefix -> (control, how notes name it)
READS_SIDES = {"native": (NATIVE_CONTROL, "native"), "zero": (ZERO_IMAGE, "zero-image")}
BEATS_SIDES = {
    "plain": (PLAIN, "plain-graft"), "zero": (ZERO_IMAGE, "zero-image"), "shuffled": (SHUFFLED_IMAGE, "shuffled-image"),
}


def _side(results: pl.DataFrame, control: str, keys: list[str], name: str, **extra: pl.Expr) -> pl.DataFrame:
    """One control's valid MSEs per key: count, mean, min, max and the seeds they came from."""
    mse = pl.col("eval_mse")
    return control_rows(results, control).group_by(keys).agg(**{
        f"{name}_n": mse.count().cast(pl.Int64),
        f"{name}_mean": mse.mean(),
        f"{name}_min": mse.min(),
        f"{name}_max": mse.max(),
        f"{name}_seeds": pl.col("seed").filter(mse.is_not_null()).unique().sort(),
    }, **extra)


def _joined(frames: list[pl.DataFrame], on: list[str], sides: dict[str, tuple[str, str]]) -> pl.DataFrame:
    """Every key any side has (a missing side's count is 0, its statistics null)."""
    out = reduce(lambda x, y: x.join(y, on=on, how="full", coalesce=True), frames)
    return out.with_columns(pl.col(*(f"{name}_n" for name in sides)).fill_null(0))


def _judged(*names: str) -> pl.Expr:
    """Every named side has valid rows."""
    return pl.all_horizontal(*(pl.col(f"{name}_n") > 0 for name in names))


def _below(low: str, high: str) -> pl.Expr:
    """low's worst seed below high's best: low beats high on every seed (null unless both have valid rows)."""
    return pl.when(_judged(low, high)).then(pl.col(f"{low}_max") < pl.col(f"{high}_min"))


def _note(sides: dict[str, tuple[str, str]]) -> pl.Expr:
    """Which side has no valid rows (so no verdict), or, with a verdict, which sides hold one seed ('every seed' is
    that seed)."""
    missing = [pl.when(pl.col(f"{n}_n") == 0).then(pl.lit(f"no valid {label} rows")) for n, (_, label) in sides.items()]
    single = pl.concat_str([
        pl.when((pl.col(f"{n}_n") > 0) & (pl.col(f"{n}_seeds").list.len() == 1))
        .then(pl.format("{} (seed {})", pl.lit(label), pl.col(f"{n}_seeds").list.first()))
        for n, (_, label) in sides.items()
    ], separator=", ", ignore_nulls=True)
    one = pl.when(_judged(*sides) & (single != "")).then(
        pl.format("one seed: {} — 'every seed' is that seed", single))
    note = pl.concat_str([*missing, one], separator="; ", ignore_nulls=True)
    return pl.when(note != "").then(note)


def native_vs_zero_image(results: pl.DataFrame, *, by_encoder: bool = False) -> pl.DataFrame:
    """Does each backbone read its images? Per (backbone, suite): its own tower as loaded (`native` rows) against
    the zero-image control, whose rows carry the encoder whose features they replace: pooled over every encoder
    (`zero_encoders` names them), or per encoder with by_encoder=True.

    verdict: SEPARATED when the worst native seed is below the best zero-image seed, else NOT_SEPARATED; null
    (with a note) when a side has no valid rows. gap = (zero_mean - native_mean) / zero_mean, the share of the
    blind policy's error its images remove.
    """
    check(results)
    keys = CELL if by_encoder else GROUP
    names = pl.col("encoder").unique().sort().str.join(", ")
    frames = [_side(results, NATIVE_CONTROL, GROUP, "native"),
              _side(results, ZERO_IMAGE, keys, "zero", zero_encoders=names)]
    out = _joined(frames, GROUP, READS_SIDES)
    zero, native = pl.col("zero_mean"), pl.col("native_mean")
    separated = _below("native", "zero")
    return out.with_columns(
        gap=pl.when(_judged(*READS_SIDES) & (zero > 0)).then((zero - native) / zero),
        verdict=pl.when(separated).then(pl.lit(SEPARATED)).when(separated.not_()).then(pl.lit(NOT_SEPARATED)),
        note=_note(READS_SIDES),
    ).sort(keys, nulls_last=True)


def beats_image_controls(results: pl.DataFrame) -> pl.DataFrame:
    """Which encoders beat both image controls on every seed? Per (backbone, suite, encoder) with plain-graft,
    zero-image or shuffled-image rows: beats_zero / beats_shuffled = the worst plain-graft seed is below that
    control's best seed; verdict from BEATS, null (with a note) when a side has no valid rows.

    encoder_random_init: the cell's rows' one value (null where they record none, or disagree), so a reader
    can tell real weights from random-init ones.
    """
    results = conform(results)  # a table without encoder_random_init (a minimal one) reads it as null
    frames = [_side(results, control, CELL, name) for name, (control, _) in BEATS_SIDES.items()]
    controls = [control for control, _ in BEATS_SIDES.values()]
    flag = pl.col("encoder_random_init")
    weights = results.filter(pl.col("control").is_in(controls)).group_by(CELL).agg(
        encoder_random_init=pl.when(flag.n_unique() == 1).then(flag.first()))
    out = _joined(frames, CELL, BEATS_SIDES).join(weights, on=CELL, how="left")
    code = {2 * zero + shuffled: verdict for (zero, shuffled), verdict in BEATS.items()}
    beats = pl.col("beats_zero").cast(pl.Int8) * 2 + pl.col("beats_shuffled").cast(pl.Int8)
    return (
        out.with_columns(beats_zero=_below("plain", "zero"), beats_shuffled=_below("plain", "shuffled"))
        .with_columns(verdict=beats.replace_strict(code, default=None, return_dtype=pl.String),
                      note=_note(BEATS_SIDES))
        .sort(CELL)
    )
