"""`graftcache extract`: stage 1, pooled encoder features for every frame of a LeRobot dataset."""

from __future__ import annotations

import argparse

from graftcache.cli.common import (
    add_cache_flag,
    add_compute_dtype_flag,
    add_device_flags,
    int_list,
    nonneg_int,
    positive_int,
)
from graftcache.nonfinite import DROP_FLAG, KEEP_FLAG


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "extract",
        help="decode every frame once, run an encoder, pool, store fp16 features in Zarr",
        description="Decode every frame of a LeRobot dataset once, run the encoder, pool to the requested "
        "grids and store the features with a provenance manifest. Rerunning the same command reuses a "
        "complete cache or resumes an interrupted one.",
    )
    p.add_argument("--encoder", required=True,
                   help="registry name (siglip, dinov2-s, mobilenetv2, ...), timm:<name> or hf:<id-or-path>")
    p.add_argument("--dataset", required=True, help="local LeRobot dataset folder or a hub repo id in the local HF cache")
    p.add_argument("--weights", default=None, help="local weights file/folder instead of the hub id")
    p.add_argument("--random-init", action="store_true", help="random weights (labelled random-init everywhere)")
    p.add_argument("--seed", type=nonneg_int, default=0, help="seed for --random-init (default 0)")
    p.add_argument("--policy", default=None,
                   help="policy for native towers (smolvla-native, pi05-native): hub id, checkpoint folder, or 'tiny' "
                   "(the tiny backbone natively trained on --dataset by `graftcache train-tiny`)")
    p.add_argument("--grids", default="8x8", help="pooled grids, e.g. 8x8,16x16 (default 8x8: SmolVLA's grid)")
    p.add_argument("--cameras", default=None, help="comma-separated camera names (default: all)")
    p.add_argument("--episodes", type=int_list, default=None, help="episode subset, e.g. 0-9,20")
    p.add_argument("--frame-stride", type=positive_int, default=1, metavar="K",
                   help="features for every K-th frame of each episode (frame_index %% K == 0); actions stay at the "
                   "full rate for action chunks. Part of the cache key (default 1: every frame)")
    p.add_argument("--batch-size", type=positive_int, default=32)
    p.add_argument("--num-workers", type=nonneg_int, default=2, help="decode worker processes (0: decode in-process)")
    add_compute_dtype_flag(p)
    p.add_argument("--block-frames", type=positive_int, default=256, help="frames per Zarr shard / resumable unit")
    p.add_argument("--no-progress", action="store_true")
    p.add_argument(KEEP_FLAG, dest="allow_nonfinite", action="store_true",
                   help="cache frames whose state, action or features hold NaN/inf instead of refusing the dataset "
                   f"(`fit` then refuses the cache unless {DROP_FLAG} drops those frames)")
    add_cache_flag(p)
    add_device_flags(p, dtype_help="stored feature dtype (default fp16)")
    p.set_defaults(func=run)


def _policy(args: argparse.Namespace) -> str | None:
    """`--policy tiny` names the tiny backbone natively trained on this dataset: find its folder."""
    if args.policy != "tiny":
        return args.policy
    from graftcache.backbones.native import NATIVE_SUFFIX
    from graftcache.fit.lookup import dataset_fingerprint, resolve_policy
    from graftcache.store import cache_root

    backbone = args.encoder.removesuffix(NATIVE_SUFFIX)
    return resolve_policy(backbone, "tiny", dataset_fingerprint(args.dataset), cache_root(args.cache), args.dataset)


def run(args: argparse.Namespace) -> int:
    from graftcache.extract import ExtractRequest, extract
    from graftcache.pooling import parse_grids

    req = ExtractRequest(
        dataset=args.dataset,
        encoder=args.encoder,
        grids=tuple(parse_grids(args.grids)),
        cameras=tuple(c.strip() for c in args.cameras.split(",")) if args.cameras else None,
        episodes=args.episodes,
        frame_stride=args.frame_stride,
        weights=args.weights,
        random_init=args.random_init,
        seed=args.seed,
        policy=_policy(args),
        dtype=args.dtype,
        compute_dtype=args.compute_dtype,
        device=args.device,
        batch_size=args.batch_size,
        num_workers=args.num_workers,
        block_frames=args.block_frames,
        cache=args.cache,
        progress=not args.no_progress,
        allow_nonfinite=args.allow_nonfinite,
    )
    result = extract(req)
    print(result.key)
    return 0
