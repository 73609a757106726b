"""Flags and value parsers shared by several commands, defined once.

Values are checked by type and range here, at parse time, so a bad flag is argparse's one-line
usage error before any work starts (never a traceback from deep inside a run).
"""

from __future__ import annotations

import argparse
from collections.abc import Callable

from graftcache.runtime import COMPUTE_DTYPES

SEEDS_HELP = ("how many seeds: N runs seeds 0..N-1 (N >= 1); a comma list or range such as 0,2 or 0-4 "
              "names the seeds instead. For one particular seed use --seed, e.g. --seed 0")
SEED_LIST_HELP = "explicit seed list: 0, 0,2, 0-4 or 0-3,7 (exclusive with --seeds)"


def int_at_least(low: int) -> Callable[[str], int]:
    """argparse type: an integer >= `low`."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
        if value < low:
            raise argparse.ArgumentTypeError(f"{value} must be >= {low}")
        return value

    parse.__name__ = f"integer >= {low}"
    return parse


positive_int = int_at_least(1)
nonneg_int = int_at_least(0)


def positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not value > 0:
        raise argparse.ArgumentTypeError(f"{value} must be > 0")
    return value


def fraction(text: str) -> float:
    """argparse type: a number strictly between 0 and 1."""
    value = positive_float(text)
    if value >= 1:
        raise argparse.ArgumentTypeError(f"{value} must be < 1")
    return value


def int_list(text: str) -> tuple[int, ...]:
    """'0,1,2', '0-9' or '0-3,7' -> sorted distinct non-negative ints; anything else is an ArgumentTypeError."""
    out: set[int] = set()
    for part in text.split(","):
        part = part.strip()
        if not part:
            continue
        lo, dash, hi = part.partition("-")
        try:
            first, last = int(lo), int(hi) if dash else int(lo)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r}: {part!r} is not N or N-M with N, M >= 0") from None
        if first < 0 or last < first:
            raise argparse.ArgumentTypeError(f"{text!r}: {part!r} is not an ascending range of non-negative ints")
        out.update(range(first, last + 1))
    if not out:
        raise argparse.ArgumentTypeError(f"{text!r} names no value")
    return tuple(sorted(out))


def seeds_value(text: str) -> tuple[int, ...]:
    """--seeds: a bare integer N is a count (seeds 0..N-1); a comma list or a range lists the seeds."""
    text = text.strip()
    if text.isdigit():
        n = int(text)
        if n < 1:
            raise argparse.ArgumentTypeError(
                f"{text!r}: --seeds N counts seeds and needs N >= 1; to run seed {n} alone use --seed {n}")
        return tuple(range(n))
    return int_list(text)


def add_seed_flags(p: argparse.ArgumentParser, *, default_count: int) -> None:
    group = p.add_mutually_exclusive_group()
    group.add_argument("--seeds", type=seeds_value, default=tuple(range(default_count)), metavar="N|LIST",
                       help=f"{SEEDS_HELP} (default {default_count})")
    group.add_argument("--seed", type=int_list, dest="seeds", metavar="LIST", help=SEED_LIST_HELP)


def add_cache_flag(p: argparse.ArgumentParser) -> None:
    p.add_argument("--cache", metavar="DIR|URL", default=None,
                   help="cache root: a folder or an s3:// gs:// az:// URL "
                   "(default: $GRAFTCACHE_HOME or ~/.cache/graftcache)")


def add_compute_dtype_flag(p: argparse.ArgumentParser, *aliases: str) -> None:
    p.add_argument("--compute-dtype", *aliases, dest="compute_dtype", default="auto", choices=COMPUTE_DTYPES,
                   help="model compute precision. auto (default): bf16 where the device computes it natively "
                        "(CUDA with bf16, CPUs with AVX512-BF16/AMX), else fp32. The resolved dtype is recorded "
                        "in manifests, keys and rows")


def add_device_flags(p: argparse.ArgumentParser, *, dtype_help: str) -> None:
    p.add_argument("--device", default="cpu", help="cpu, cuda or cuda:N (default: cpu)")
    p.add_argument("--dtype", default="fp16", choices=("fp16", "bf16", "fp32"), help=dtype_help)
