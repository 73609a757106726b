"""`graftcache train-tiny`: natively train a tiny SmolVLA / pi0.5 so that the diagnostic has a
backbone whose image tokens matter (no released weights can be fetched offline)."""

from __future__ import annotations

import argparse

from graftcache.cli.common import add_compute_dtype_flag, nonneg_int, positive_int


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("train-tiny", help="natively train a tiny backbone on a dataset (all parameters, on pixels)",
                       description="Train lerobot's SmolVLA or pi0.5 at tiny sizes, all parameters and its own vision "
                       "tower, on a LeRobot dataset. The checkpoint is cached and found again by --policy tiny.")
    p.add_argument("--backbone", required=True, choices=("smolvla", "pi05"))
    p.add_argument("--dataset", default="data/libero_sample")
    p.add_argument("--steps", type=positive_int, default=None)
    p.add_argument("--seed", type=nonneg_int, default=None)
    p.add_argument("--out", default=None, help="checkpoint folder (default: <cache>/policies/tiny-<backbone>-<hash>)")
    p.add_argument("--force", action="store_true", help="retrain even if a checkpoint exists")
    p.add_argument("--device", default="cpu")
    add_compute_dtype_flag(p)
    p.add_argument("--cache", default=None)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from dataclasses import replace

    from graftcache.pretrain import DEFAULT_TINY_TRAIN, train_tiny

    overrides = {k: v for k, v in (("steps", args.steps), ("seed", args.seed), ("compute_dtype", args.compute_dtype))
                 if v is not None}
    cfg = replace(DEFAULT_TINY_TRAIN, **overrides)
    print(train_tiny(args.backbone, args.dataset, cfg=cfg, cache=args.cache, device=args.device, out=args.out,
                     force=args.force))
    return 0
