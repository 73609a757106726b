"""Hand-built results tables with answers worked out by hand (see the comments next to each suite).

Encoders siglip, dinov2-s, resnet18; backbones smolvla (small) and pi05 (large); seeds 0, 1, 2.

- libero_spatial: smolvla ranks siglip < dinov2-s < resnet18; on pi05 dinov2-s is best but siglip's seeds
  overlap it (in the top tier), resnet18 is far off -> transfers; tau_b = 1/3; seed pairings: seed 0
  agrees (siglip/siglip), seeds 1 and 2 disagree (siglip/dinov2-s).
- libero_object: smolvla winner siglip; on pi05 every siglip seed is worse than every dinov2-s seed
  -> does not transfer; tau_b = -1/3; all three seed pairings disagree.
- libero_goal: siglip and resnet18 only on smolvla -> one shared encoder -> insufficient data.
- libero_10: siglip and dinov2-s tie for first on smolvla (means 2.0); pi05 has seed 0 only with siglip ==
  dinov2-s == 1.0 < resnet18 -> single-seed tier = exact ties {dinov2-s, siglip} -> transfers (flagged);
  tau_b = 1.0 (a pair tied on both sides).
Controls on smolvla/libero_spatial: zero-image and shuffled-image for siglip (far), zero-image for
resnet18 (within noise); native 1.0 and native-graft seeds 1.1/1.2/1.3 -> non-neutrality 0.2;
pi05/libero_spatial has native 2.0 but no native-graft.
"""

from __future__ import annotations

from typing import Any

import polars as pl

from graftcache.results import SCHEMA, make_run_id, validate

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


def command(backbone: str, suite: str, encoder: str, control: str, seed: int) -> str:
    return (f"graftcache fit --backbone {backbone} --encoder {encoder} --suite {suite} "
            f"--control {control} --seed {seed}")


def row(backbone: str, suite: str, encoder: str, seed: int, eval_mse: float | None, **over: Any) -> dict:
    """One complete SCHEMA row; keyword overrides replace any column."""
    control = over.get("control", "none")
    cell = {"backbone": backbone, "suite": suite, "encoder": encoder, "seed": seed, "control": control}
    base = {
        "run_id": make_run_id({**cell, **{k: v for k, v in over.items() if k != "run_id"}}),
        **cell,
        "policy": "tiny",
        "policy_sha256": "0" * 64,
        "cache_key": f"key-{encoder}-{suite}",
        "pool_grid": "8x8",
        "objective": "eval" if control == "native" else "flow",
        "steps": 100,
        "lr": 1e-3,
        "batch_size": 8,
        "train_loss_final": 0.5,
        "eval_mse": eval_mse,
        "eval_mse_first": eval_mse,
        "eval_mse_raw": eval_mse,
        "n_eval_frames": 120,
        "n_eval_episodes": 4,
        "eval_split_seed": 0,
        "wall_s": 1.0,
        "device": "cpu",
        "random_init": False,
        "graftcache_version": "0.1.0",
        "command": command(backbone, suite, encoder, control, seed),
    }
    base.update(over)
    return base


def table(rows: list[dict]) -> pl.DataFrame:
    """Rows -> a validated results table (every SCHEMA column present and typed)."""
    return validate(pl.DataFrame(rows, schema=SCHEMA))


def plain_rows(cells: dict[tuple[str, str, str], list[float]] = PLAIN_MSE, **over: Any) -> list[dict]:
    return [row(b, s, e, seed, v, **over) for (b, s, e), vals in cells.items() for seed, v in enumerate(vals)]


def control_rows(cells: dict[tuple[str, str, str, str], list[float]] = CONTROL_MSE) -> list[dict]:
    return [
        row(b, s, e, seed, v, control=c)
        for (b, s, e, c), vals in cells.items()
        for seed, v in enumerate(vals)
    ]


def full_table(*, random_init_for: tuple[str, str] | None = None) -> pl.DataFrame:
    """The whole hand-built table; random_init_for=(backbone, encoder) marks those rows random-init."""
    rows = plain_rows() + control_rows()
    if random_init_for:
        for r in rows:
            r["random_init"] = (r["backbone"], r["encoder"]) == random_init_for
    return table(rows)


def write_results(path, frame: pl.DataFrame | None = None):
    """Write a results Parquet file (the hand-built table by default) and return its path."""
    (frame if frame is not None else full_table()).write_parquet(path)
    return path
