"""`graftcache push KEY DEST | pull KEY SRC`: copy a complete cache between roots, verified on arrival."""

from __future__ import annotations

import argparse

from graftcache.cli.common import add_cache_flag, add_flag
from graftcache.requests import FitRequest

# command -> (help, description, the other root's name, whether --cache is the source)
DIRECTIONS: dict[str, tuple[str, str, str, bool]] = {
    "push": ("publish a local cache to another root (e.g. s3://bucket/prefix)",
             "Copy complete cache KEY from --cache to DEST, verify every block there, then mark it complete. "
             "An interrupted push resumes; a copy that verifies is not sent again.", "dest", True),
    "pull": ("fetch a cache from another root into the local one, verified",
             "Copy complete cache KEY from SOURCE into --cache, verify every block, then mark it complete. "
             "A damaged source block is refused by name; an interrupted pull resumes.", "source", False),
}


def add_parser(sub: argparse._SubParsersAction) -> None:
    for command, (summary, description, other, _) in DIRECTIONS.items():
        p = sub.add_parser(command, help=summary, description=description)
        p.add_argument("key")
        p.add_argument(other, help=f"{other} root: a folder or an s3:// gs:// az:// URL")
        add_cache_flag(p)
        add_flag(p, FitRequest, "accept_numerics_drift",
                 help="copy even when this environment computes the cache's features differently from the one "
                 "that made it (its numerics fingerprint, recomputed here before copying)")
        p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from graftcache.encoders.fingerprint import check_numerics
    from graftcache.store import FeatureCache, open_root
    from graftcache.store.push_pull import copy_cache

    _, _, other, from_cache = DIRECTIONS[args.command]
    here, there = open_root(args.cache), open_root(getattr(args, other))
    source, dest = (here, there) if from_cache else (there, here)
    # the numbers must be what this environment computes before they are handed on or taken in
    check_numerics(FeatureCache.in_root(source, args.key)).enforce(args.command, accept=args.accept_numerics_drift,
                                                                    log=print)
    copy_cache(source, dest, args.key)
    return 0
