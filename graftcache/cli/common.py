"""Flags and value parsers shared by several commands, defined once.

Values are checked by type and range here, at parse time, so a bad flag is argparse's one-line
usage error before any work starts (never a traceback from deep inside a run). A flag that sets a
request field (graftcache.requests) takes its default from that field (`add_field`), and the request
is built from the parsed namespace by field name (`request_from`), so a field's default has one home.
"""

from __future__ import annotations

import argparse
import dataclasses
from collections.abc import Callable
from typing import Any, TypeVar

from graftcache.checks import SEEDS, IntList
from graftcache.runtime import COMPUTE_DTYPES

R = TypeVar("R")
#: What the parser itself puts in every namespace (the subcommand's name and handler): never request fields.
PARSER_KEYS = frozenset({"command", "func"})

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


def nonneg_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"{value} must be >= 0")
    return value


def fraction(text: str) -> float:
    """argparse type: a number strictly between 0 and 1."""
    value = positive_float(text)
    if value >= 1:
        raise argparse.ArgumentTypeError(f"{value} must be < 1")
    return value


def int_list(text: str, rule: IntList = SEEDS) -> tuple[int, ...]:
    """'0,1,2', '0-9' or '0-3,7' -> sorted distinct non-negative ints; anything else (a value named twice
    included) is an ArgumentTypeError.

    The ranges are measured before they are expanded, against `rule`'s bounds (the request field's rule, e.g.
    FitRequest.RULES["seeds"]), so 0-100000000000 is refused at once instead of filling memory."""
    ranges: list[tuple[int, int]] = []
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
        if last > rule.high:
            raise argparse.ArgumentTypeError(f"{text!r}: {last} is past the largest {rule.what}, {rule.high}")
        ranges.append((first, last))
    if not ranges:
        raise argparse.ArgumentTypeError(f"{text!r} names no value")
    count = sum(last - first + 1 for first, last in ranges)  # an upper bound: overlaps count twice
    if count > rule.most:
        raise argparse.ArgumentTypeError(f"{text!r} names {count} {rule.what}s; at most {rule.most}")
    values = sorted(v for first, last in ranges for v in range(first, last + 1))
    repeated = sorted({a for a, b in zip(values, values[1:]) if a == b})
    if repeated:  # `--seed 0,0` is a typo, not one seed: nothing is merged silently
        raise argparse.ArgumentTypeError(f"{text!r} names {', '.join(map(str, repeated))} more than once")
    return tuple(values)


def ints(rule: IntList) -> Callable[[str], tuple[int, ...]]:
    """argparse type: `int_list` bounded by `rule` (a request field's IntList rule)."""

    def parse(text: str) -> tuple[int, ...]:
        return int_list(text, rule)

    parse.__name__ = f"{rule.what} list"
    return parse


def shard_value(text: str) -> tuple[int, int]:
    """'i/N' -> (i, N) with 0 <= i < N: shard i of N (extract --shard)."""
    index, slash, count = text.partition("/")
    try:
        value = (int(index), int(count)) if slash else None
    except ValueError:
        value = None
    if value is None or not 0 <= value[0] < value[1]:
        raise argparse.ArgumentTypeError(f"{text!r} is not i/N with 0 <= i < N (e.g. 0/4 ... 3/4)")
    return value


def name_list(text: str) -> tuple[str, ...]:
    """'a, b,c' -> ("a", "b", "c") (empty parts dropped)."""
    return tuple(part.strip() for part in text.split(",") if part.strip())


def grids_value(text: str) -> tuple[str, ...]:
    """'native, 4x4' -> ("native", "4x4") (graftcache.pooling.grid_names); a malformed grid is argparse's usage
    error."""
    from graftcache.errors import GraftcacheError
    from graftcache.pooling import grid_names

    try:
        return grid_names(text)
    except GraftcacheError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def seeds_value(text: str, rule: IntList = SEEDS) -> tuple[int, ...]:
    """--seeds: a bare integer N is a count (seeds 0..N-1, at most `rule.most`); a comma list or a range lists
    the seeds."""
    text = text.strip()
    if text.isdigit():
        n = int(text)
        if n < 1:
            raise argparse.ArgumentTypeError(
                f"{text!r}: --seeds N counts seeds and needs N >= 1; to run seed {n} alone use --seed {n}")
        if n > rule.most:
            raise argparse.ArgumentTypeError(f"{text!r}: --seeds N counts seeds; at most {rule.most}")
        return tuple(range(n))
    return int_list(text, rule)


def camera_map_value(text: str) -> str:
    """--camera-map: POLICY=CACHE pairs (graftcache/cameras.py), written back in canonical form; a malformed or
    duplicated pair is argparse's usage error naming it."""
    from graftcache.cameras import CameraError, format_camera_map, parse_camera_map

    try:
        return format_camera_map(parse_camera_map(text))
    except CameraError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def default_of(request: type, name: str) -> Any:
    """The default of a request dataclass field: its one home, for the flag that sets it."""
    spec = {f.name: f for f in dataclasses.fields(request)}[name]
    return spec.default_factory() if spec.default_factory is not dataclasses.MISSING else spec.default


def _shown(value: Any) -> str:
    return ",".join(map(str, value)) if isinstance(value, tuple) else str(value)


def add_field(p: argparse.ArgumentParser, request: type, name: str, *aliases: str, help: str = "",
              shown: str | None = None, overrides: bool = False, **kw: Any) -> None:
    """`--<name>` for a request field, defaulting to the field's default (named in the help unless None;
    `shown` overrides how it is written). With `overrides` the flag overrides a value read elsewhere (a
    recipe): it is absent from the namespace unless given (see `given`)."""
    default = default_of(request, name)
    if default is not None and kw.get("action") not in ("store_true", "store_false"):
        help = f"{help} (default {shown or _shown(default)})".strip()
    p.add_argument(f"--{name.replace('_', '-')}", *aliases, dest=name, help=help or None,
                   default=argparse.SUPPRESS if overrides else default, **kw)


def given(request: type, args: argparse.Namespace) -> dict[str, Any]:
    """The fields of `request` set on the command line by flags made with `add_field(..., overrides=True)`."""
    names = {f.name for f in dataclasses.fields(request)} - PARSER_KEYS
    return {n: v for n, v in vars(args).items() if n in names}


def request_from(request: type[R], args: argparse.Namespace, **values: Any) -> R:
    """The request whose fields are the namespace's values of the same name, then `values`."""
    names = {f.name for f in dataclasses.fields(request)} - PARSER_KEYS - set(values)
    return request(**{n: v for n, v in vars(args).items() if n in names}, **values)


def add_seed_flags(p: argparse.ArgumentParser, request: type) -> None:
    group = p.add_mutually_exclusive_group()
    default = default_of(request, "seeds")
    rule = request.RULES["seeds"]
    group.add_argument("--seeds", type=lambda text: seeds_value(text, rule), default=default,
                       metavar="N|LIST", help=f"{SEEDS_HELP} (default: seeds {_shown(default)})")
    group.add_argument("--seed", type=ints(rule), dest="seeds", metavar="LIST", help=SEED_LIST_HELP)


def add_progress_flag(p: argparse.ArgumentParser) -> None:
    p.add_argument("--no-progress", dest="progress", action="store_false", help="no progress bars or lines")


def add_cache_flag(p: argparse.ArgumentParser) -> None:
    p.add_argument("--cache", metavar="DIR|URL", default=None,
                   help="cache root: a folder or an s3:// gs:// az:// URL "
                   "(default: $GRAFTCACHE_HOME or ~/.cache/graftcache)")


def add_cells_per_pass_flag(p: argparse.ArgumentParser, *, overrides: bool = False) -> None:
    """--cells-per-pass N (FitRequest.cells_per_pass); `overrides`: over a recipe's [fit] table."""
    from graftcache.requests import FitRequest

    add_field(p, FitRequest, "cells_per_pass", type=positive_int, metavar="N", overrides=overrides,
              help="cells (seeds, image controls, encoders of one grid and width) trained together in one forward and "
              "backward of the frozen backbone, each with its own projector, loss, optimiser and random streams; "
              "rows equal one-cell-at-a-time rows up to float rounding and keep their run_ids; lora, align and "
              "native cells run alone (default: per backbone and device, graftcache.fit.passes.CELLS_PER_PASS: 1 "
              "on CPU)")


def add_compute_dtype_flag(p: argparse.ArgumentParser, request: type, *aliases: str) -> None:
    add_field(p, request, "compute_dtype", *aliases, choices=COMPUTE_DTYPES,
              help="model compute precision. auto: bf16 where the device computes it natively (CUDA with bf16, "
                   "CPUs with AVX512-BF16/AMX), else fp32. The resolved dtype is recorded in manifests, keys and rows")


def add_executor_flags(p: argparse.ArgumentParser, *, overrides: bool = False) -> None:
    """Where the work runs (ExecutorSettings; all but --executor apply to --executor ray only). `overrides`: the
    flags override a recipe's [executor] table, whose values (else the defaults shown) hold where none is given."""
    from graftcache.executors import EXECUTORS
    from graftcache.requests import ExecutorSettings

    def flag(name: str, **kw: Any) -> None:
        add_field(p, ExecutorSettings, name, overrides=overrides, **kw)

    flag("executor", choices=tuple(EXECUTORS),
         help="local: this process; ray: Ray tasks (every node must see the dataset, the cache root and the "
         "results folder: a shared file system or an s3:// cache root)")
    flag("address", metavar="ADDR", help="a running Ray cluster to join (auto, ray://HOST:10001); "
         "default: start a Ray instance on this machine")
    flag("gpus_per_task", type=nonneg_float, metavar="G",
         help="GPUs per task; a fraction shares one GPU between tasks (default: 1 with --device cuda, else 0)")
    flag("cpus_per_task", type=positive_float, metavar="C", help="CPUs per task, also its torch threads")
    flag("shards", type=positive_int, metavar="N",
         help="tasks per extraction (default: as many as the cluster runs at once)")
    flag("max_retries", type=nonneg_int, metavar="N",
         help="reruns of a task whose worker or node died (a task that raised an error is not rerun)")


def add_camera_map_flag(p: argparse.ArgumentParser, request: type, help: str) -> None:
    add_field(p, request, "camera_map", type=camera_map_value, metavar="POLICY=CACHE,...", help=help)


def add_device_flag(p: argparse.ArgumentParser, request: type) -> None:
    add_field(p, request, "device", help="cpu, cuda or cuda:N")
