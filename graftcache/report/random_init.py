"""The report's random-init banner: per backbone, whether its own weights and each encoder's were random-init.

Rows record the two apart (`encoder_random_init`, `backbone_random_init`) and their union (`random_init`). The demo
grafts ImageNet encoders into tiny train-tiny backbones: every row is random-init somewhere, but the encoders'
weights are real, and a reader comparing encoders needs to know which are. Rows that record only the union (tables
from older versions or other tools) are listed as such, never guessed apart.

A native tower (`smolvla-native`) is the policy's own tower: its rows' `encoder_random_init` is the backbone's
(graftcache.results.schema), random-init or trained by train-tiny alike, so it is listed as the backbone's weights,
never among the encoders with random-init weights.
"""

from __future__ import annotations

import polars as pl

from graftcache import analysis as A
from graftcache.backbone_registry import NATIVE_SUFFIX
from graftcache.report.document import Alert, Block

LEAD = ("A random-init encoder's MSEs say nothing about pretrained representations; a random-init or train-tiny "
        "backbone is not a released policy, so rankings on it stand in for the released one's only as a proxy.")


def _names(rows: pl.DataFrame) -> str:
    return ", ".join(sorted(set(rows["encoder"].to_list())))


def _backbone_words(rows: pl.DataFrame) -> str | None:
    """What one backbone's rows say of its own weights (None: no row records them apart)."""
    known = rows.drop_nulls("backbone_random_init")
    if not len(known):
        return None
    rand = int(known["backbone_random_init"].sum())
    share = "all" if rand == len(rows) else f"{rand} of"
    if not rand:
        return "released (not random-init) weights"
    return f"random-init or train-tiny weights ({share} {len(rows)} rows)"


def _encoder_words(rows: pl.DataFrame) -> list[str]:
    """Which encoders ran on random-init weights and which on real ones, and the rows recording only the union."""
    known = rows.drop_nulls("encoder_random_init")
    native = pl.col("encoder").str.ends_with(NATIVE_SUFFIX)
    own = known.filter(pl.col("encoder_random_init"), native)
    rand = known.filter(pl.col("encoder_random_init"), ~native)
    real = known.filter(~pl.col("encoder_random_init"))
    union = rows.filter(pl.col("encoder_random_init").is_null(), pl.col("random_init").fill_null(False))
    return [
        *([f"encoders with random-init weights: {_names(rand)}"] if len(rand) else []),
        *([f"the policy's own tower, with the backbone's weights: {_names(own)}"] if len(own) else []),
        *([f"real weights: {_names(real)}"] if len(real) else []),
        *([f"encoder and backbone not recorded apart (only random_init), random-init in one or both: "
           f"{_names(union)} ({len(union)} rows)"] if len(union) else []),
    ]


def random_init_warning(a: A.Analysis) -> list[Block]:
    """One line per backbone with random-init weights anywhere in its rows (nothing when no row has any)."""
    r = a.results
    rand = r.filter(pl.col("random_init").fill_null(False) | pl.col("encoder_random_init").fill_null(False)
                    | pl.col("backbone_random_init").fill_null(False))
    if not len(rand):
        return []
    present = set(rand["backbone"].to_list())
    order = [b for b in a.backbones if b in present] + sorted(present - set(a.backbones))
    lines = []
    for b in order:
        rows = r.filter(pl.col("backbone") == b)
        own = _backbone_words(rows)
        words = [*([f"backbone {own}"] if own else []), *_encoder_words(rows)]
        lines.append(f"{A.backbone_label(b)} (`{b}`): " + "; ".join(words))
    lead = f"{len(rand)} of {len(r)} rows were produced with random-init weights in the encoder or the backbone. {LEAD}"
    return [Alert("random-init weights", (lead, *lines))]
