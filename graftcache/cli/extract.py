"""`graftcache extract`: stage 1, pooled encoder features for every frame of a LeRobot dataset."""

from __future__ import annotations

import argparse

from graftcache.cli.common import add_flags, request_from
from graftcache.requests import ExecutorSettings, ExtractRequest


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "extract",
        help="decode every frame once, run an encoder, store its fp16 patch grid in Zarr",
        description="Decode every frame of a LeRobot dataset once, run the encoder and store its own patch grid "
        "(and any pooled grids asked for) with a provenance manifest. Stage 2 pools the stored grid to each "
        "backbone's token grid when it reads it. Rerunning the same command reuses a complete cache or resumes "
        "an interrupted one.",
    )
    add_flags(p, ExtractRequest)  # every flag is an ExtractRequest or ExecutorSettings field (graftcache/requests.py)
    add_flags(p, ExecutorSettings)
    p.set_defaults(func=run)


def _policy(args: argparse.Namespace) -> str | None:
    """`--policy tiny` names the tiny backbone trained on this dataset by train-tiny: find its folder."""
    if args.policy != "tiny":
        return args.policy
    from graftcache.backbone_registry import backbone_of_native
    from graftcache.backbones.tiny_record import resolve_policy
    from graftcache.fit.lookup import dataset_identity
    from graftcache.store import cache_root

    return resolve_policy(backbone_of_native(args.encoder), "tiny", dataset_identity(args.dataset),
                          cache_root(args.cache), args.dataset)


def run(args: argparse.Namespace) -> int:
    from graftcache.executors import get_executor

    executor = get_executor(request_from(ExecutorSettings, args))
    print(executor.extract(request_from(ExtractRequest, args, policy=_policy(args)), log=print).key)
    return 0
