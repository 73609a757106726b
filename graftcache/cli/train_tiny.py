"""`graftcache train-tiny`: train a tiny backbone (--backbone) so that the diagnostic has a
backbone whose image tokens matter (no released weights can be fetched offline)."""

from __future__ import annotations

import argparse

from graftcache.cli.common import add_cache_flag, add_flag, add_flags, request_from
from graftcache.requests import FitRequest, TinyTrainConfig


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("train-tiny", help="train a tiny backbone on a dataset (all parameters, on pixels)",
                       description="Train a backbone's lerobot policy at tiny sizes, all parameters and its own vision "
                       "tower, on a LeRobot dataset. The checkpoint is cached and found again by --policy tiny.")
    add_flag(p, FitRequest, "backbone")
    p.add_argument("--dataset", default="data/libero_sample")
    add_flags(p, TinyTrainConfig)  # the recipe's settings (graftcache/requests.py); the rest name what and where
    p.add_argument("--out", default=None, help="checkpoint folder (default: <cache>/policies/tiny-<backbone>-<hash>)")
    p.add_argument("--force", action="store_true", help="retrain even if a checkpoint exists")
    add_flag(p, FitRequest, "device")
    add_cache_flag(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from graftcache.pretrain import train_tiny

    print(train_tiny(args.backbone, args.dataset, cfg=request_from(TinyTrainConfig, args), cache=args.cache,
                     device=args.device, out=args.out, force=args.force))
    return 0
