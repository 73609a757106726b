"""`graftcache export RUN_ID --results PATH --out DIR`: a fitted cell as a lerobot policy folder (graftcache.export)."""

from __future__ import annotations

import argparse


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("export", help="write a fitted cell as a lerobot policy (type graftcache) for lerobot-eval",
                       description="Write the cell RUN_ID of a results file as a folder lerobot loads as a policy of "
                       "type `graftcache` (lerobot-eval --policy.path=DIR): the base policy with the cell's projector "
                       "(and LoRA) grafted in, fed by the cell's encoder through the cache's preprocessing, pooling "
                       "and camera mapping. Refuses the shuffled-image control and a drifted numerics fingerprint.")
    p.add_argument("run_id", metavar="RUN_ID", help="the cell's run_id (a results row)")
    p.add_argument("--results", required=True, help="results Parquet file holding the row")
    p.add_argument("--out", required=True, help="folder to write (must not hold an export already)")
    p.add_argument("--cache", default=None, help="cache root its fit read (default: $GRAFTCACHE_HOME or "
                   "~/.cache/graftcache)")
    p.add_argument("--runs", default=None, help="folder of run folders, when its fit wrote them elsewhere (--out)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from graftcache.export.locate import check_cache_root, find_row

    check_cache_root(find_row(args.results, args.run_id), args.cache)  # before torch, lerobot and the policy load
    from graftcache.export.bundle import export_run

    export_run(args.run_id, args.results, args.out, cache=args.cache, runs=args.runs)
    return 0
