"""A hand-built table for the two findings (graftcache.analysis.findings), answers worked out by hand.

Backbones smolvla and pi05; encoders a (real weights), b (random-init), c (weights not recorded); seeds from 0.

Native vs zero-image (every encoder's zero-image rows of a backbone and suite pooled):
- smolvla/s: native 1.0, 1.1 (mean 1.05, worst 1.1); zero-image a 2.0, 2.2 and b 2.1, 2.3 (mean 2.15, best 2.0)
  -> 1.1 < 2.0: separated on every seed; gap (2.15 - 1.05) / 2.15 = 0.5116.
- pi05/s: native 1.0, 2.1 (mean 1.55); zero-image a 2.0, 3.0 (mean 2.5, best 2.0) -> the native seed 2.1 overlaps:
  not separated; gap (2.5 - 1.55) / 2.5 = 0.38.
- pi05/t: native only -> no verdict, "no valid zero-image rows"; smolvla/t: zero-image only -> "no valid native rows".
- smolvla/u: one seed each, native 1.0 < zero-image 3.0 -> separated, the note says 'every seed' is seed 0.

Encoders against both image controls (worst plain-graft seed below each control's best seed):
- smolvla/s/a: plain 1.0, 1.2 < zero-image 2.0 and < shuffled-image 1.5 -> beats both on every seed.
- smolvla/s/b: plain 1.4, 1.5 < zero-image 2.1, but 1.5 >= shuffled-image 1.45 -> beats zero-image only.
- pi05/s/a: plain 2.5, 2.6 >= zero-image 2.0 and >= shuffled-image 2.4 -> beats neither: pi05 has no encoder that
  beats both.
- pi05/s/c: plain only; smolvla/t/a: zero-image only -> no verdict, notes naming the missing controls.
- smolvla/u/a: one seed, plain 1.5 < zero-image 3.0, < shuffled-image 2.0 -> beats both, the note says one seed.
"""

from __future__ import annotations

import polars as pl

from helpers.tables import row, table

FINDINGS_MSE: dict[tuple[str, str, str, str], list[float]] = {
    ("smolvla", "s", "smolvla-native", "native"): [1.0, 1.1],
    ("smolvla", "s", "a", "none"): [1.0, 1.2],
    ("smolvla", "s", "a", "zero-image"): [2.0, 2.2],
    ("smolvla", "s", "a", "shuffled-image"): [1.5, 1.6],
    ("smolvla", "s", "b", "none"): [1.4, 1.5],
    ("smolvla", "s", "b", "zero-image"): [2.1, 2.3],
    ("smolvla", "s", "b", "shuffled-image"): [1.45, 1.7],
    ("pi05", "s", "pi05-native", "native"): [1.0, 2.1],
    ("pi05", "s", "a", "none"): [2.5, 2.6],
    ("pi05", "s", "a", "zero-image"): [2.0, 3.0],
    ("pi05", "s", "a", "shuffled-image"): [2.4, 2.45],
    ("pi05", "s", "c", "none"): [1.0, 1.1],
    ("pi05", "t", "pi05-native", "native"): [1.0],
    ("smolvla", "t", "a", "zero-image"): [2.0],
    ("smolvla", "u", "smolvla-native", "native"): [1.0],
    ("smolvla", "u", "a", "none"): [1.5],
    ("smolvla", "u", "a", "zero-image"): [3.0],
    ("smolvla", "u", "a", "shuffled-image"): [2.0],
}
ENCODER_RANDOM_INIT = {"a": False, "b": True, "c": None}


def findings_table() -> pl.DataFrame:
    """FINDINGS_MSE as a results table, each encoder's rows recording ENCODER_RANDOM_INIT."""
    return table([
        row(b, s, e, seed, v, control=c, encoder_random_init=ENCODER_RANDOM_INIT.get(e, False))
        for (b, s, e, c), vals in FINDINGS_MSE.items() for seed, v in enumerate(vals)
    ])
