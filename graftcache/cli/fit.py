"""`graftcache fit`: train only the projector into a frozen backbone from cached features."""

from __future__ import annotations

import argparse

from graftcache.cli.common import add_flags, request_from
from graftcache.requests import FitRequest


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("fit", help="fit projector-only grafts (seeds x controls) from a cache, one row per cell",
                       description="Train only LayerNorm + Linear into a frozen backbone from cached features, "
                       "across seeds and controls, and score offline action MSE on held-out episodes. Finished cells "
                       "in --results are skipped.")
    add_flags(p, FitRequest)  # every flag is a FitRequest field, declared in graftcache/requests.py
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from graftcache.fit.local import Fitter

    Fitter(request_from(FitRequest, args, command=args.command_line)).run()
    return 0
