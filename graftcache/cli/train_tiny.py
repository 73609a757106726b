"""`graftcache train-tiny`: natively train a tiny SmolVLA / pi0.5 so that the diagnostic has a
backbone whose image tokens matter (no released weights can be fetched offline)."""

from __future__ import annotations

import argparse

from graftcache.backbone_table import BACKBONES
from graftcache.cli.common import add_compute_dtype_flag, add_field, name_list, nonneg_int, positive_int, request_from
from graftcache.requests import TinyTrainConfig


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("train-tiny", help="natively train a tiny backbone on a dataset (all parameters, on pixels)",
                       description="Train lerobot's SmolVLA or pi0.5 at tiny sizes, all parameters and its own vision "
                       "tower, on a LeRobot dataset. The checkpoint is cached and found again by --policy tiny.")
    p.add_argument("--backbone", required=True, choices=tuple(BACKBONES))
    p.add_argument("--dataset", default="data/libero_sample")
    add_field(p, TinyTrainConfig, "cameras", type=name_list, metavar="A,B",
              help="the dataset cameras the policy sees, in this order (default: all of them, in the dataset's "
              "order); its config records their names, so a fit on this dataset matches them by name")
    add_field(p, TinyTrainConfig, "steps", type=positive_int)
    add_field(p, TinyTrainConfig, "seed", type=nonneg_int)
    p.add_argument("--out", default=None, help="checkpoint folder (default: <cache>/policies/tiny-<backbone>-<hash>)")
    p.add_argument("--force", action="store_true", help="retrain even if a checkpoint exists")
    p.add_argument("--device", default="cpu")
    add_compute_dtype_flag(p, TinyTrainConfig)
    p.add_argument("--cache", default=None)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from graftcache.pretrain import train_tiny

    print(train_tiny(args.backbone, args.dataset, cfg=request_from(TinyTrainConfig, args), cache=args.cache,
                     device=args.device, out=args.out, force=args.force))
    return 0
