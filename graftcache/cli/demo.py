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
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from graftcache.demo import run_demo

    report = run_demo(args.recipe, args.out)
    print(f"report: {report.markdown}\n        {report.html}")
    return 0
