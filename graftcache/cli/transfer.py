"""`graftcache push KEY DEST | pull KEY SRC`: copy a complete cache between roots, verified on arrival."""

from __future__ import annotations

import argparse

from graftcache.cli.common import add_cache_flag


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("push", help="publish a local cache to another root (e.g. s3://bucket/prefix)",
                       description="Copy complete cache KEY from --cache to DEST, verify every block there, then "
                       "mark it complete. An interrupted push resumes; a verified copy is not sent again.")
    p.add_argument("key")
    p.add_argument("dest", help="destination root: a folder or s3:// gs:// az:// URL")
    add_cache_flag(p)
    p.set_defaults(func=run_push)
    p = sub.add_parser("pull", help="fetch a cache from another root into the local one, verified",
                       description="Copy complete cache KEY from SRC into --cache, verify every block, then mark "
                       "it complete. A damaged source block is refused by name; an interrupted pull resumes.")
    p.add_argument("key")
    p.add_argument("source", help="source root: a folder or s3:// gs:// az:// URL")
    add_cache_flag(p)
    p.set_defaults(func=run_pull)


def run_push(args: argparse.Namespace) -> int:
    from graftcache.store import open_root
    from graftcache.store.transfer import copy_cache

    copy_cache(open_root(args.cache), open_root(args.dest), args.key)
    return 0


def run_pull(args: argparse.Namespace) -> int:
    from graftcache.store import open_root
    from graftcache.store.transfer import copy_cache

    copy_cache(open_root(args.source), open_root(args.cache), args.key)
    return 0
