"""`graftcache fit`: train only the projector into a frozen backbone from cached features."""

from __future__ import annotations

import argparse

from graftcache.cli.common import (
    add_cache_flag,
    add_compute_dtype_flag,
    add_seed_flags,
    fraction,
    nonneg_int,
    positive_float,
    positive_int,
)


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("fit", help="fit projector-only grafts (seeds x controls) from a cache, one row per cell",
                       description="Train only LayerNorm + Linear into a frozen SmolVLA / pi0.5 from cached features, "
                       "across seeds and controls, and score offline action MSE on held-out episodes. Finished cells "
                       "in --results are skipped.")
    p.add_argument("--backbone", required=True, choices=("smolvla", "pi05"))
    p.add_argument("--policy", default="tiny",
                   help="hub id (HF cache), local checkpoint folder, or 'tiny' (the natively trained tiny backbone)")
    p.add_argument("--encoder", required=True, help="encoder whose cache to graft (registry name)")
    p.add_argument("--dataset", default=None, help="dataset the cache must come from (path or hub id)")
    p.add_argument("--cache-key", default=None, help="use this cache (when several match)")
    p.add_argument("--native-cache-key", default=None, help="native tower cache for native controls / align")
    p.add_argument("--suite", required=True, help="LIBERO suite, e.g. libero_spatial")
    add_seed_flags(p, default_count=3)
    p.add_argument("--controls", default="",
                   help="comma list: native, native-graft, zero-image, shuffled-image, pool-HxW, lora")
    p.add_argument("--objective", default="flow", choices=("flow", "align"),
                   help="flow: the policy's loss; align: closed-form ridge onto the native tokens (cheap screening)")
    p.add_argument("--steps", type=positive_int, default=300)
    p.add_argument("--lr", type=positive_float, default=1e-3)
    p.add_argument("--batch-size", type=positive_int, default=16)
    p.add_argument("--eval-fraction", type=fraction, default=0.2, help="held-out share of each task's episodes")
    p.add_argument("--eval-split-seed", type=nonneg_int, default=0)
    p.add_argument("--eval-frames", type=positive_int, default=None, help="cap on scored held-out frames (evenly spaced)")
    p.add_argument("--num-denoise-steps", type=positive_int, default=None)
    p.add_argument("--lora-rank", type=positive_int, default=8)
    p.add_argument("--device", default="cpu")
    add_compute_dtype_flag(p, "--dtype")
    p.add_argument("--results", default="results.parquet")
    p.add_argument("--out", default=None,
                   help="run folder for projectors (default: runs/ beside --results; never the cache root)")
    p.add_argument("--no-progress", action="store_true")
    add_cache_flag(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from graftcache.fit.run import Fitter, FitRequest

    req = FitRequest(
        backbone=args.backbone, encoder=args.encoder, suite=args.suite, policy=args.policy, dataset=args.dataset,
        cache_key=args.cache_key, native_cache_key=args.native_cache_key, seeds=args.seeds,
        controls=tuple(c.strip() for c in args.controls.split(",") if c.strip()), objective=args.objective,
        steps=args.steps, lr=args.lr, batch_size=args.batch_size, eval_fraction=args.eval_fraction,
        eval_split_seed=args.eval_split_seed, eval_frames=args.eval_frames,
        num_denoise_steps=args.num_denoise_steps, lora_rank=args.lora_rank, device=args.device,
        compute_dtype=args.compute_dtype, results=args.results, out=args.out, cache=args.cache,
        progress=not args.no_progress,
    )
    Fitter(req).run()
    return 0
