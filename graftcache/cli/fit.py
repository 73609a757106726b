"""`graftcache fit`: train only the projector into a frozen backbone from cached features."""

from __future__ import annotations

import argparse

from graftcache.backbone_table import BACKBONES
from graftcache.cli.common import (
    add_cache_flag,
    add_camera_map_flag,
    add_cells_per_pass_flag,
    add_compute_dtype_flag,
    add_device_flag,
    add_field,
    add_progress_flag,
    add_seed_flags,
    fraction,
    name_list,
    nonneg_int,
    positive_float,
    positive_int,
    request_from,
)
from graftcache.datasets.suites import SUITE_ORDER
from graftcache.fit.controls import CONTROLS, POOL_PREFIX
from graftcache.fit.objectives import OBJECTIVES
from graftcache.requests import FitRequest


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("fit", help="fit projector-only grafts (seeds x controls) from a cache, one row per cell",
                       description="Train only LayerNorm + Linear into a frozen SmolVLA / pi0.5 from cached features, "
                       "across seeds and controls, and score offline action MSE on held-out episodes. Finished cells "
                       "in --results are skipped.")
    p.add_argument("--backbone", required=True, choices=tuple(BACKBONES))
    add_field(p, FitRequest, "policy",
              help="hub id (HF cache), local checkpoint folder, or 'tiny' (the natively trained tiny backbone)")
    p.add_argument("--encoder", required=True, help="encoder whose cache to graft (registry name)")
    add_field(p, FitRequest, "dataset", help="dataset the cache must come from (path or hub id)")
    add_field(p, FitRequest, "cache_key", help="use this cache (when several match)")
    add_field(p, FitRequest, "native_cache_key", help="native tower cache for native controls / align")
    add_camera_map_flag(p, FitRequest, "which cache camera feeds each policy camera, e.g. image=agentview,"
                        "image2=eye_in_hand: needed when the names differ (cameras are matched by name, never by "
                        "position); every row records the mapping used (camera_map)")
    p.add_argument("--suite", required=True, help=f"LIBERO suite: {', '.join(SUITE_ORDER)}")
    add_seed_flags(p, FitRequest)
    add_field(p, FitRequest, "controls", type=name_list, shown="none",
              help=f"comma list: {', '.join(c for c in CONTROLS if c != 'none')}, {POOL_PREFIX}HxW")
    add_field(p, FitRequest, "objective", choices=tuple(OBJECTIVES),
              help="flow: the policy's loss; align: closed-form ridge onto the native tokens (cheap screening)")
    add_field(p, FitRequest, "steps", type=positive_int)
    add_field(p, FitRequest, "lr", type=positive_float)
    add_field(p, FitRequest, "batch_size", type=positive_int)
    add_field(p, FitRequest, "buffer_mib", type=positive_int,
              help="MiB of training features held in the shuffle buffer: with --num-workers x 2 prefetched cache "
              "blocks, what bounds the fit's memory whatever the suite's size (more mixes episodes better); reading in "
              "this process (--num-workers 0), up to as much again of read blocks is kept for the next cells")
    add_field(p, FitRequest, "eval_fraction", type=fraction, help="held-out share of each task's episodes")
    add_field(p, FitRequest, "eval_split_seed", type=nonneg_int)
    add_field(p, FitRequest, "eval_frames", type=positive_int, help="cap on scored held-out frames (evenly spaced)")
    add_field(p, FitRequest, "num_denoise_steps", type=positive_int)
    add_field(p, FitRequest, "lora_rank", type=positive_int)
    add_device_flag(p, FitRequest)
    add_field(p, FitRequest, "num_workers", type=nonneg_int,
              help="processes reading and pooling cached features ahead of the model (0: in this process)")
    add_cells_per_pass_flag(p)
    add_compute_dtype_flag(p, FitRequest, "--dtype")
    add_field(p, FitRequest, "results")
    add_field(p, FitRequest, "out", help="run folder for projectors (default: runs/ beside --results; never the cache root)")
    add_progress_flag(p)
    add_field(p, FitRequest, "drop_nonfinite", action="store_true",
              help="drop frames whose features, state or action chunk hold NaN/inf (a cache holding any is "
              "refused otherwise); the results row records how many (n_dropped_nonfinite)")
    add_field(p, FitRequest, "accept_numerics_drift", action="store_true",
              help="fit even when this environment computes a cache's features differently from the one that "
              "made it (its numerics fingerprint); each row records the measured drift")
    add_cache_flag(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from graftcache.fit.run import Fitter

    Fitter(request_from(FitRequest, args)).run()
    return 0
