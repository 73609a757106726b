"""Hand-built results tables with answers worked out by hand (see the comments next to each suite).

Encoders siglip, dinov2-s, resnet18; backbones smolvla (small) and pi05 (large); seeds 0, 1, 2.
LADDER_MSE (below) is a three-backbone table for the ladder questions.

- libero_spatial: smolvla ranks siglip < dinov2-s < resnet18; on pi05 dinov2-s is best but siglip's seeds
  overlap it (in the top tier), resnet18 is far off -> smolvla -> pi05 transfers; the pi05 winner dinov2-s
  is outside the smolvla tier {siglip} -> pi05 -> smolvla does not; tau_b = 1/3; seed pairings: seed 0
  agrees (siglip/siglip), seeds 1 and 2 disagree (siglip/dinov2-s); seed-level cells: seed 0 transfers both
  ways, seeds 1 and 2 neither way.
- libero_object: smolvla winner siglip; on pi05 every siglip seed is worse than every dinov2-s seed
  -> does not transfer, either way (tiers {dinov2-s} on pi05, {siglip} on smolvla); tau_b = -1/3; all three
  seed pairings disagree, no seed-level cell transfers.
- libero_goal: siglip and resnet18 only on smolvla -> one shared encoder -> insufficient data both ways.
- libero_10: siglip and dinov2-s tie for first on smolvla (means 2.0, both in its tier); pi05 has seed 0
  only with siglip == dinov2-s == 1.0 < resnet18 -> single-seed tier = exact ties {dinov2-s, siglip} ->
  transfers both ways (smolvla -> pi05 flagged); tau_b = 1.0 (a pair tied on both sides). Seed 0 alone:
  smolvla top-1 siglip (1.0) is in pi05's tie -> transfers; pi05's tied winners are not both in smolvla's
  seed-0 tier {siglip} -> does not; seeds 1 and 2 were not run on pi05 -> insufficient data.
So 3 of 6 judged comparisons transfer (2 insufficient) and 3 of 14 judged seed-level cells (10 insufficient).

BOTH_WAYS_MSE and NEAR_TIE_MSE (below) are smaller tables for one question each.
Controls on smolvla/libero_spatial: zero-image and shuffled-image for siglip (far), zero-image for
resnet18 (within noise); native 1.0 and native-graft seeds 1.1/1.2/1.3 -> non-neutrality 0.2;
pi05/libero_spatial has native 2.0 but no native-graft.
"""

from __future__ import annotations

import itertools
from typing import Any

import numpy as np
import polars as pl

from graftcache.results import FORMAT_VERSION, REPORT_COLUMNS, SCHEMA, make_run_id, validate
from graftcache.results.upgrade import with_policy_ids

PLAIN_MSE: dict[tuple[str, str, str], list[float]] = {
    ("smolvla", "libero_spatial", "siglip"): [1.0, 1.1, 1.2],
    ("smolvla", "libero_spatial", "dinov2-s"): [2.0, 2.1, 2.2],
    ("smolvla", "libero_spatial", "resnet18"): [3.0, 3.1, 3.2],
    ("pi05", "libero_spatial", "siglip"): [1.0, 1.5, 2.0],
    ("pi05", "libero_spatial", "dinov2-s"): [1.2, 1.4, 1.6],
    ("pi05", "libero_spatial", "resnet18"): [5.0, 5.0, 5.0],
    ("smolvla", "libero_object", "siglip"): [1.0, 1.0, 1.0],
    ("smolvla", "libero_object", "dinov2-s"): [1.5, 1.6, 1.7],
    ("smolvla", "libero_object", "resnet18"): [2.0, 2.1, 2.2],
    ("pi05", "libero_object", "siglip"): [3.0, 3.1, 3.2],
    ("pi05", "libero_object", "dinov2-s"): [1.0, 1.1, 1.2],
    ("pi05", "libero_object", "resnet18"): [2.0, 2.1, 2.2],
    ("smolvla", "libero_goal", "siglip"): [1.0, 1.1, 1.2],
    ("smolvla", "libero_goal", "dinov2-s"): [2.0, 2.1, 2.2],
    ("smolvla", "libero_goal", "resnet18"): [3.0, 3.1, 3.2],
    ("pi05", "libero_goal", "dinov2-s"): [1.0, 1.1, 1.2],
    ("smolvla", "libero_10", "siglip"): [1.0, 2.0, 3.0],
    ("smolvla", "libero_10", "dinov2-s"): [2.0, 2.0, 2.0],
    ("smolvla", "libero_10", "resnet18"): [4.0, 4.0, 4.0],
    ("pi05", "libero_10", "siglip"): [1.0],
    ("pi05", "libero_10", "dinov2-s"): [1.0],
    ("pi05", "libero_10", "resnet18"): [2.0],
}

CONTROL_MSE: dict[tuple[str, str, str, str], list[float]] = {
    ("smolvla", "libero_spatial", "siglip", "zero-image"): [3.0, 3.1, 3.2],
    ("smolvla", "libero_spatial", "siglip", "shuffled-image"): [2.0, 2.2, 2.4],
    ("smolvla", "libero_spatial", "resnet18", "zero-image"): [3.0, 3.05, 3.1],
    ("smolvla", "libero_spatial", "smolvla-native", "native"): [1.0],
    ("smolvla", "libero_spatial", "smolvla-native", "native-graft"): [1.1, 1.2, 1.3],
    ("pi05", "libero_spatial", "pi05-native", "native"): [2.0],
}


# What each hand-built row records as its policy's parameter count (graftcache.analysis.ladder orders by it).
PARAMS = {"smolvla": 450_000_000, "pi05": 3_300_000_000}


def command(backbone: str, suite: str, encoder: str, control: str, seed: int) -> str:
    return (f"graftcache fit --backbone {backbone} --encoder {encoder} --suite {suite} "
            f"--control {control} --seed {seed}")


def row(backbone: str, suite: str, encoder: str, seed: int, eval_mse: float | None, **over: Any) -> dict:
    """One SCHEMA row, every column but `eval_mse_episodes` filled; keyword overrides replace any column."""
    control = over.get("control", "none")
    cell = {"backbone": backbone, "suite": suite, "encoder": encoder, "seed": seed, "control": control}
    base = {
        "run_id": make_run_id({**cell, **{k: v for k, v in over.items() if k != "run_id"}}),
        **cell,
        "format_version": FORMAT_VERSION,
        "backbone_params": PARAMS.get(backbone),
        "policy": "tiny",
        "policy_sha256": "0" * 64,
        "cache_key": f"key-{encoder}-{suite}",
        "pool_grid": "8x8",
        "objective": "eval" if control == "native" else "flow",
        "steps": 100,
        "lr": 1e-3,
        "batch_size": 8,
        "buffer_mib": 0 if control == "native" else 2048,
        "train_loss_final": 0.5,
        "eval_mse": eval_mse,
        "eval_mse_first": eval_mse,
        "eval_mse_raw": eval_mse,
        "eval_mse_arm": eval_mse,  # both parts equal: their dims-weighted mean is eval_mse
        "eval_mse_gripper": eval_mse,
        "n_eval_frames": 120,
        "n_eval_episodes": 4,
        "eval_split_seed": 0,
        "eval_split": "graftcache",
        "wall_s": 1.0,
        "device": "cpu",
        "compute_dtype": "fp32",
        "random_init": False,
        "encoder_random_init": False,
        "backbone_random_init": False,
        "n_dropped_nonfinite": 0,
        "numerics_drift": 0.0,
        "camera_map": "image=image,image2=image2",
        "graftcache_version": "0.1.0",
        "command": command(backbone, suite, encoder, control, seed),
        "cells_per_pass": 1,
        "activation_checkpointing": "off",
        "eval_batch_size": 64,
        "eval_seconds_per_frame": 0.01,
        "attention": "eager",
        "kernels": "cpu:avx2",
        "compile": False,
        "eval_fraction": 0.2,
        "eval_frames": 120,
        "num_denoise_steps": 10,
        "lora_rank": 8 if control == "lora" else 0,  # the cell's: 0 but for the lora control
    }
    base.update(over)
    return base


def table(rows: list[dict]) -> pl.DataFrame:
    """Rows -> a validated results table (every SCHEMA column present and typed); a row without a policy_id gets the
    one its cell columns give (graftcache.results.upgrade.with_policy_ids: native rows of every seed are one policy)."""
    return validate(with_policy_ids(pl.DataFrame(rows, schema=SCHEMA)))


def plain_rows(cells: dict[tuple[str, str, str], list[float]] = PLAIN_MSE, **over: Any) -> list[dict]:
    return [row(b, s, e, seed, v, **over) for (b, s, e), vals in cells.items() for seed, v in enumerate(vals)]


def control_rows(cells: dict[tuple[str, str, str, str], list[float]] = CONTROL_MSE) -> list[dict]:
    return [
        row(b, s, e, seed, v, control=c)
        for (b, s, e, c), vals in cells.items()
        for seed, v in enumerate(vals)
    ]


def full_table(*, random_init_for: tuple[str, str] | None = None) -> pl.DataFrame:
    """The whole hand-built table; random_init_for=(backbone, encoder) marks that encoder's rows on that backbone
    as of a random-init encoder."""
    rows = plain_rows() + control_rows()
    if random_init_for:
        for r in rows:
            r["random_init"] = r["encoder_random_init"] = (r["backbone"], r["encoder"]) == random_init_for
    return table(rows)


def write_results(path, frame: pl.DataFrame | None = None):
    """Write a results Parquet file (the hand-built table by default) and return its path."""
    (frame if frame is not None else full_table()).write_parquet(path)
    return path


# Encoders a, b, c; seeds 0, 1, 2. Tiers follow from exact_p_greater (the bootstrap enumerated exhaustively).
# s1: smolvla a < b < c, all separated -> tier {a}; pi05 b best (mean 1.333), a (1.433) overlaps it
#     (P = 0.687) -> tier {a, b}: smolvla -> pi05 transfers, pi05 -> smolvla does not.
#     Per seed: seed 0 pi05 top-1 a (1.0 < 1.2) -> transfers both ways; seeds 1, 2 pi05 top-1 b -> neither.
# s2: smolvla a best, b overlaps it (P = 0.770) -> tier {a, b}; pi05 b best, a and c separated -> tier {b}:
#     smolvla -> pi05 does not transfer, pi05 -> smolvla transfers.
#     Per seed: smolvla top-1 always a, pi05 top-1 always b -> no cell transfers either way.
# Comparisons: 2 of 4 transfer; seed-level cells: 2 of 12.
BOTH_WAYS_MSE: dict[tuple[str, str, str], list[float]] = {
    ("smolvla", "s1", "a"): [1.0, 1.1, 1.2],
    ("smolvla", "s1", "b"): [2.0, 2.1, 2.2],
    ("smolvla", "s1", "c"): [3.0, 3.1, 3.2],
    ("pi05", "s1", "a"): [1.0, 1.6, 1.7],
    ("pi05", "s1", "b"): [1.2, 1.3, 1.5],
    ("pi05", "s1", "c"): [5.0, 5.0, 5.0],
    ("smolvla", "s2", "a"): [1.0, 1.1, 1.2],
    ("smolvla", "s2", "b"): [1.05, 1.15, 1.25],
    ("smolvla", "s2", "c"): [3.0, 3.0, 3.0],
    ("pi05", "s2", "a"): [2.0, 2.1, 2.2],
    ("pi05", "s2", "b"): [1.0, 1.1, 1.2],
    ("pi05", "s2", "c"): [3.0, 3.0, 3.0],
}

# smolvla a far ahead of b -> tier {a}; pi05 b best (1.4) but a (1.5) overlaps it (P = 0.624) -> pi05's tier
# holds every encoder: smolvla -> pi05 is a near-tie band (the old code called it "transfers");
# pi05 -> smolvla: b is outside {a} -> does not transfer.
NEAR_TIE_MSE: dict[tuple[str, str, str], list[float]] = {
    ("smolvla", "s", "a"): [1.0, 1.1, 1.2],
    ("smolvla", "s", "b"): [2.0, 2.1, 2.2],
    ("pi05", "s", "a"): [1.0, 1.5, 2.0],
    ("pi05", "s", "b"): [1.2, 1.4, 1.6],
}


# Three backbones whose names do not sort by size: kilo (0.5B) < alpha (2B) < mu (7B). Encoders a, b, c.
# Suite s, every seed separated from every other encoder's (tiers hold the winner alone, P = 1):
#   kilo a < b < c, alpha a < c < b, mu c < b < a.
#   kilo -> alpha transfers (a in {a}) and back; kilo -> mu and alpha -> mu do not (a not in {c}), nor back
#   (c not in {a}). Headline: kilo's winner a is not in mu's tier {c}; the ranking transfers kilo -> alpha and
#   breaks at alpha -> mu. Every seed orders the encoders as the means do, so each seed-level cell repeats its
#   pooled verdict. Kendall tau-b: kilo/alpha 1/3, kilo/mu -1, alpha/mu -1/3.
# Suite t: kilo and alpha are NEAR_TIE_MSE's two backbones (kilo tier {a}; alpha's tier {b, a} holds both), mu
#   ran a alone: kilo -> alpha is a near-tie band, alpha -> kilo does not transfer (b not in {a}), every pair
#   with mu is insufficient data (1 shared encoder). Headline: insufficient data; rungs: near-tie band,
#   insufficient data; no break, 1 rung unjudged. Seed level kilo/alpha: seed 0 alpha a 1.0 < b 1.2 -> transfers
#   both ways; seeds 1 and 2 alpha b best -> does not transfer either way.
LADDER_PARAMS = {"kilo": 500_000_000, "alpha": 2_000_000_000, "mu": 7_000_000_000}
_LOW, _MID, _HIGH = [1.0, 1.1, 1.2], [2.0, 2.1, 2.2], [3.0, 3.1, 3.2]
LADDER_MSE: dict[tuple[str, str, str], list[float]] = {
    ("kilo", "s", "a"): _LOW, ("kilo", "s", "b"): _MID, ("kilo", "s", "c"): _HIGH,
    ("alpha", "s", "a"): _LOW, ("alpha", "s", "b"): _HIGH, ("alpha", "s", "c"): _MID,
    ("mu", "s", "a"): _HIGH, ("mu", "s", "b"): _MID, ("mu", "s", "c"): _LOW,
    ("kilo", "t", "a"): [1.0, 1.1, 1.2], ("kilo", "t", "b"): [2.0, 2.1, 2.2],
    ("alpha", "t", "a"): [1.0, 1.5, 2.0], ("alpha", "t", "b"): [1.2, 1.4, 1.6],
    ("mu", "t", "a"): [1.0, 1.1, 1.2],
}


def ladder_table(cells: dict[tuple[str, str, str], list[float]] = LADDER_MSE) -> pl.DataFrame:
    """LADDER_MSE as a results table, each row recording its backbone's LADDER_PARAMS."""
    return table([row(b, s, e, seed, v, backbone_params=LADDER_PARAMS[b])
                  for (b, s, e), vals in cells.items() for seed, v in enumerate(vals)])


def exact_p_greater(x: list[float], y: list[float]) -> float:
    """P(mean(x*) > mean(y*)) over every equally likely bootstrap resample of x and of y, enumerated."""
    mx = np.array([np.mean(t) for t in itertools.product(x, repeat=len(x))])
    my = np.array([np.mean(t) for t in itertools.product(y, repeat=len(y))])
    return float((mx[:, None] > my[None, :]).mean())


def minimal_table(cells: dict[tuple[str, str, str], list[float]]) -> pl.DataFrame:
    """Only results.REPORT_COLUMNS, as a table typed in from a paper would have them (seed as Int32)."""
    rows = [
        {"backbone": b, "suite": s, "encoder": e, "control": "none", "seed": seed, "eval_mse": v}
        for (b, s, e), vals in cells.items()
        for seed, v in enumerate(vals)
    ]
    return pl.DataFrame(rows, schema_overrides={"seed": pl.Int32}).select(REPORT_COLUMNS)
