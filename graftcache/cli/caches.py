"""`graftcache ls | info KEY | verify KEY`: inspect and check feature caches."""

from __future__ import annotations

import argparse
import json

from rich.console import Console
from rich.table import Table

from graftcache.cli.common import add_cache_flag


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("ls", help="list feature caches", description="List feature caches under the cache root.")
    add_cache_flag(p)
    p.set_defaults(func=run_ls)
    p = sub.add_parser("info", help="print a cache's manifest", description="Print the manifest of cache KEY as JSON.")
    p.add_argument("key")
    add_cache_flag(p)
    p.set_defaults(func=run_info)
    p = sub.add_parser("verify", help="re-check a cache's checksums and completeness",
                       description="Re-read every block of cache KEY and compare with its checksums. "
                       "Exit code 0: complete and intact; 1: incomplete or corrupt.")
    p.add_argument("key")
    p.add_argument("--numerics", action="store_true",
                   help="also recompute the cache's numerics probe here (loads its encoder) and print the largest "
                        "difference and the library versions that differ; drift or no fingerprint: exit code 1")
    add_cache_flag(p)
    p.set_defaults(func=run_verify)


def _open(args: argparse.Namespace):
    from graftcache.store import FeatureCache, open_root

    return FeatureCache.in_root(open_root(args.cache), args.key)


def run_ls(args: argparse.Namespace) -> int:
    """Healthy caches as a table; a cache that cannot be opened is a row saying why (never a crash)."""
    from graftcache.errors import CacheError
    from graftcache.store import open_root, scan_caches

    root = open_root(args.cache)
    table = Table(title=f"feature caches in {root}")
    for col in ("key", "dataset", "encoder", "weights", "grids", "cameras", "frames", "size", "status"):
        table.add_column(col)
    caches, broken = scan_caches(root)
    for c in caches:
        m = c.manifest
        try:
            weights = m.weights_label
            status = "complete" if c.complete else ("incomplete" if c.initialized else "initialising")
            table.add_row(c.key, m.dataset.repo_id or m.dataset.source, m.encoder_name, weights,
                          ",".join(m.grids + list(m.extras)), ",".join(m.cameras),
                          str(m.n_frames), f"{c.size_bytes() / 2**20:.1f} MiB", status)
        except CacheError as e:  # its folder holds a symbolic link (never followed, so not sized)
            table.add_row(c.key, *[""] * 7, f"BROKEN: {e}")
    for b in broken:
        table.add_row(b.key, *[""] * 7, f"BROKEN: {b.reason}")
    console = Console()
    if not console.is_terminal:  # piped or captured: print whole keys instead of folding to 80 columns
        console = Console(width=240)
    console.print(table)
    return 0


def run_info(args: argparse.Namespace) -> int:
    c = _open(args)
    print(json.dumps({**c.manifest.to_dict(), "complete": c.complete, "layout": {k: v for k, v in c.layout.items()
                                                                      if k != "static_checksums"}},
                     indent=2, default=str))
    return 0


def run_verify(args: argparse.Namespace) -> int:
    c = _open(args)
    problems = c.verify()
    for p in problems:
        print(p)
    if not problems:
        print(f"{c.key}: complete, {c.n_frames} frames, all checksums match")
    numerics_ok = True
    if args.numerics:
        from graftcache.encoders.fingerprint import check_numerics

        check = check_numerics(c)
        print(check.line())
        numerics_ok = check.status == "match"
    return 0 if not problems and numerics_ok else 1
