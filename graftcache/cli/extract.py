"""`graftcache extract`: stage 1, pooled encoder features for every frame of a LeRobot dataset."""

from __future__ import annotations

import argparse

from graftcache.backbone_table import BACKBONES, native_name
from graftcache.cli.common import (
    add_cache_flag,
    add_camera_map_flag,
    add_compute_dtype_flag,
    add_device_flag,
    add_executor_flags,
    add_field,
    add_progress_flag,
    grids_value,
    ints,
    name_list,
    nonneg_int,
    positive_int,
    request_from,
    shard_value,
)
from graftcache.nonfinite import DROP_FLAG
from graftcache.pooling import NATIVE
from graftcache.requests import ExecutorSettings, ExtractRequest
from graftcache.runtime import DTYPES


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "extract",
        help="decode every frame once, run an encoder, store its fp16 patch grid in Zarr",
        description="Decode every frame of a LeRobot dataset once, run the encoder and store its own patch grid "
        "(and any pooled grids asked for) with a provenance manifest. Stage 2 pools the stored grid to each "
        "backbone's token grid when it reads it. Rerunning the same command reuses a complete cache or resumes "
        "an interrupted one.",
    )
    p.add_argument("--encoder", required=True,
                   help="registry name (siglip, dinov2-s, mobilenetv2, ...), timm:<name> or hf:<id-or-path>")
    p.add_argument("--dataset", required=True, help="local LeRobot dataset folder or a hub repo id in the local HF cache")
    add_field(p, ExtractRequest, "weights", help="local weights file/folder instead of the hub id")
    add_field(p, ExtractRequest, "random_init", action="store_true", help="random weights (labelled random-init everywhere)")
    add_field(p, ExtractRequest, "seed", type=nonneg_int, help="seed for --random-init")
    add_field(p, ExtractRequest, "policy",
              help=f"policy for native towers ({', '.join(native_name(b) for b in BACKBONES)}): hub id, checkpoint "
              "folder, or 'tiny' (the tiny backbone natively trained on --dataset by `graftcache train-tiny`)")
    add_field(p, ExtractRequest, "grids", type=grids_value,
              help=f"grids to store: {NATIVE} (the encoder's own patch grid, unpooled; `fit` pools it to each "
              f"backbone's token grid as it reads it) and/or pooled HxW grids, e.g. {NATIVE},4x4 or 8x8,16x16. "
              f"{NATIVE} and the encoder's grid spelled out make the same cache")
    add_field(p, ExtractRequest, "cameras", type=name_list, help="comma-separated camera names (default: all)")
    add_camera_map_flag(p, ExtractRequest, "native towers: which dataset camera feeds each policy camera where "
                        "the names differ (checked before decoding; the cache keeps the dataset's camera names)")
    add_field(p, ExtractRequest, "episodes", type=ints(ExtractRequest.RULES["episodes"]),
              help="episode subset, e.g. 0-9,20")
    add_field(p, ExtractRequest, "frame_stride", type=positive_int, metavar="K",
              help="features for every K-th frame of each episode (frame_index %% K == 0); actions stay at the "
              "full rate for action chunks. Part of the cache key (1: every frame)")
    add_field(p, ExtractRequest, "batch_size", type=positive_int)
    add_field(p, ExtractRequest, "num_workers", type=nonneg_int, help="decode worker processes (0: decode in-process)")
    add_compute_dtype_flag(p, ExtractRequest)
    add_field(p, ExtractRequest, "block_frames", type=positive_int, help="frames per Zarr shard / resumable unit")
    add_field(p, ExtractRequest, "shard", type=shard_value, metavar="i/N",
              help="write only the i-th of N contiguous ranges of blocks, so that N processes (or machines sharing "
              "an object-store root) extract one cache together; the last to finish marks it complete. Not part "
              "of the cache key; rerun a shard to resume it")
    add_progress_flag(p)
    add_field(p, ExtractRequest, "allow_nonfinite", action="store_true",
              help="cache frames whose state, action or features hold NaN/inf instead of refusing the dataset "
              f"(`fit` then refuses the cache unless {DROP_FLAG} drops those frames)")
    add_cache_flag(p)
    add_device_flag(p, ExtractRequest)
    add_field(p, ExtractRequest, "dtype", choices=tuple(DTYPES), help="stored feature dtype")
    add_executor_flags(p)
    p.set_defaults(func=run)


def _policy(args: argparse.Namespace) -> str | None:
    """`--policy tiny` names the tiny backbone natively trained on this dataset: find its folder."""
    if args.policy != "tiny":
        return args.policy
    from graftcache.backbone_table import backbone_of_native
    from graftcache.backbones.tiny_record import resolve_policy
    from graftcache.fit.lookup import dataset_fingerprint
    from graftcache.store import cache_root

    return resolve_policy(backbone_of_native(args.encoder), "tiny", dataset_fingerprint(args.dataset),
                          cache_root(args.cache), args.dataset)


def run(args: argparse.Namespace) -> int:
    from graftcache.executors import get_executor

    executor = get_executor(request_from(ExecutorSettings, args))
    print(executor.extract(request_from(ExtractRequest, args, policy=_policy(args)), log=print).key)
    return 0
