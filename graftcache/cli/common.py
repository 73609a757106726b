"""Flags shared by several commands, defined once."""

from __future__ import annotations

import argparse


def add_cache_flag(p: argparse.ArgumentParser) -> None:
    p.add_argument("--cache", metavar="DIR", default=None,
                   help="cache root (default: $GRAFTCACHE_HOME or ~/.cache/graftcache)")


def add_device_flags(p: argparse.ArgumentParser, *, dtype_help: str) -> None:
    p.add_argument("--device", default="cpu", help="cpu, cuda or cuda:N (default: cpu)")
    p.add_argument("--dtype", default="fp16", choices=("fp16", "bf16", "fp32"), help=dtype_help)


def parse_int_list(text: str) -> tuple[int, ...]:
    """'0,1,2' or '0-9' or '0-3,7' -> (0, 1, 2, ...)."""
    out: list[int] = []
    for part in text.split(","):
        part = part.strip()
        if "-" in part:
            lo, hi = part.split("-", 1)
            out.extend(range(int(lo), int(hi) + 1))
        elif part:
            out.append(int(part))
    return tuple(out)
