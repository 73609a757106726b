"""`graftcache demo`: the whole diagnostic, offline, on the bundled LIBERO sample (cli/demo.toml)."""

from __future__ import annotations

import argparse


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("demo", help="the whole diagnostic offline on the bundled LIBERO sample, then the report",
                       description="Train the tiny backbones (train-tiny) if they are not cached, extract the demo "
                       "encoders (two with real ImageNet weights beside random-init ViT families), fit the demo "
                       "recipe's cells with controls, and write the report. Rerunning reuses every cache and finished "
                       "cell.")
    p.add_argument("--recipe", default=None, help="recipe to run (default: cli/demo.toml of this checkout)")
    p.add_argument("--out", default=None, help="report folder (default: <results folder>/report)")
    p.add_argument("--closed-loop", action="store_true",
                   help="also fit the recipe on more seeds and roll its cells out in the LIBERO simulator on "
                   "perturbed scenes (graftcache/demo_closed_loop.py), for the report's offline-vs-closed-loop "
                   "figure; into demo/closed_loop/ under the cache root. Needs `make setup-libero`; under 30 minutes "
                   "on 2 cores")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if args.closed_loop:
        from graftcache.demo_closed_loop import run_closed_loop_demo

        report = run_closed_loop_demo(args.recipe, args.out)
        print("\n".join(report.findings))
    else:
        from graftcache.demo import run_demo

        report = run_demo(args.recipe, args.out)
    print(f"report: {report.markdown}\n        {report.html}")
    return 0
