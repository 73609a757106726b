"""How a setting's value is read from a flag's text and written back as one: one `Codec` per kind of value.

The CLI parses a flag with its field's codec (graftcache.cli.common), and `graftcache.sweep.command_line` writes a
request's values back with the same codec, so what a row records as "the command" parses back to the same values.
A codec is picked from the field's type (`codec_for`) unless the field names one (SHARD, GRIDS, SEEDS_COUNT,
CAMERA_MAP). Bad text raises BadText, one phrase that argparse prints as its one-line usage error.
Nothing here imports more than the standard library and graftcache's light modules.
"""

from __future__ import annotations

import argparse
import types
import typing
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from graftcache.checks import SEEDS, IntList


class BadText(argparse.ArgumentTypeError):
    """A flag's text that is not a value of its kind (the message is one phrase naming the text, which argparse
    prints as it is)."""


@dataclass(frozen=True)
class Codec:
    """`parse(text, rule)` -> value (BadText when malformed; `rule` is the field's, for bounds known before
    expanding a range) and `write(value)` -> text that parses back to the value; `metavar` for help."""

    parse: Callable[[str, Any], Any]
    write: Callable[[Any], str]
    metavar: str | None = None


def _number(kind: type, what: str) -> Callable[[str, Any], Any]:
    def parse(text: str, rule: Any) -> Any:
        try:
            return kind(text)
        except ValueError:
            raise BadText(f"{text!r} is not {what}") from None

    return parse


def int_list(text: str, rule: IntList = SEEDS) -> tuple[int, ...]:
    """'0,1,2', '0-9' or '0-3,7' -> sorted distinct non-negative ints; anything else (a value named twice
    included) is BadText.

    The ranges are measured before they are expanded, against `rule`'s bounds (the request field's rule, e.g.
    FitRequest's seeds), so 0-100000000000 is refused at once instead of filling memory."""
    ranges: list[tuple[int, int]] = []
    for part in text.split(","):
        part = part.strip()
        if not part:
            continue
        lo, dash, hi = part.partition("-")
        try:
            first, last = int(lo), int(hi) if dash else int(lo)
        except ValueError:
            raise BadText(f"{text!r}: {part!r} is not N or N-M with N, M >= 0") from None
        if first < 0 or last < first:
            raise BadText(f"{text!r}: {part!r} is not an ascending range of non-negative ints")
        if last > rule.high:
            raise BadText(f"{text!r}: {last} is past the largest {rule.what}, {rule.high}")
        ranges.append((first, last))
    if not ranges:
        raise BadText(f"{text!r} names no value")
    count = sum(last - first + 1 for first, last in ranges)  # an upper bound: overlaps count twice
    if count > rule.most:
        raise BadText(f"{text!r} names {count} {rule.what}s; at most {rule.most}")
    values = sorted(v for first, last in ranges for v in range(first, last + 1))
    repeated = sorted({a for a, b in zip(values, values[1:], strict=False) if a == b})
    if repeated:  # `--seed 0,0` is a typo, not one seed: nothing is merged silently
        raise BadText(f"{text!r} names {', '.join(map(str, repeated))} more than once")
    return tuple(values)


def seeds_value(text: str, rule: IntList = SEEDS) -> tuple[int, ...]:
    """--seeds: a bare integer N is a count (seeds 0..N-1, at most `rule.most`); a comma list or a range lists
    the seeds."""
    text = text.strip()
    if text.isdigit():
        n = int(text)
        if n < 1:
            raise BadText(f"{text!r}: --seeds N counts seeds and needs N >= 1; to run seed {n} alone use --seed {n}")
        if n > rule.most:
            raise BadText(f"{text!r}: --seeds N counts seeds; at most {rule.most}")
        return tuple(range(n))
    return int_list(text, rule)


def shard_value(text: str) -> tuple[int, int]:
    """'i/N' -> (i, N) with 0 <= i < N: shard i of N (extract --shard)."""
    index, slash, count = text.partition("/")
    try:
        value = (int(index), int(count)) if slash else None
    except ValueError:
        value = None
    if value is None or not 0 <= value[0] < value[1]:
        raise BadText(f"{text!r} is not i/N with 0 <= i < N (e.g. 0/4 ... 3/4)")
    return value


def name_list(text: str) -> tuple[str, ...]:
    """'a, b,c' -> ("a", "b", "c") (empty parts dropped)."""
    return tuple(part.strip() for part in text.split(",") if part.strip())


def _grids(text: str, rule: Any) -> tuple[str, ...]:
    from graftcache.errors import GraftcacheError
    from graftcache.pooling import grid_names

    try:
        return grid_names(text)
    except GraftcacheError as e:
        raise BadText(str(e)) from None


def _camera_map(text: str, rule: Any) -> str:
    """POLICY=CACHE pairs (graftcache/cameras.py), in canonical form; a malformed or duplicated pair names it."""
    from graftcache.cameras import CameraError, format_camera_map, parse_camera_map

    try:
        return format_camera_map(parse_camera_map(text))
    except CameraError as e:
        raise BadText(str(e)) from None


def _joined(value: Any) -> str:
    return ",".join(map(str, value))


INT = Codec(_number(int, "an integer"), str)
FLOAT = Codec(_number(float, "a number"), str)
TEXT = Codec(lambda text, rule: text, str)
NAMES = Codec(lambda text, rule: name_list(text), _joined, "A,B")
INTS = Codec(lambda text, rule: int_list(text, rule or SEEDS), _joined, "LIST")
#: --seeds: a count N or a list; written back as a list (with the `--seed` flag: "--seeds 3" would be a count).
SEEDS_COUNT = Codec(lambda text, rule: seeds_value(text, rule or SEEDS), _joined, "N|LIST")
SHARD = Codec(lambda text, rule: shard_value(text), lambda v: f"{v[0]}/{v[1]}", "i/N")
GRIDS = Codec(_grids, _joined, "GRIDS")
CAMERA_MAP = Codec(_camera_map, str, "POLICY=CACHE,...")

#: The codec of each plain field type (its `| None` dropped); other types name a codec on their field.
BY_TYPE: dict[Any, Codec] = {int: INT, float: FLOAT, str: TEXT, tuple[str, ...]: NAMES, tuple[int, ...]: INTS}


def without_none(hint: Any) -> Any:
    """`X | None` -> X; anything else unchanged."""
    if typing.get_origin(hint) in (typing.Union, types.UnionType):
        rest = [a for a in typing.get_args(hint) if a is not type(None)]
        if len(rest) == 1:
            return rest[0]
    return hint


def codec_for(hint: Any) -> Codec:
    hint = without_none(hint)
    if hint not in BY_TYPE:
        raise TypeError(f"no codec for a field of type {hint}; name one on the field (graftcache.settings.setting)")
    return BY_TYPE[hint]


def matches(value: Any, hint: Any) -> bool:
    """Whether a value read from a file (TOML lists already turned into tuples) fits a field's type hint."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if hint is Any:
        return True
    if origin in (typing.Union, types.UnionType):
        return any(matches(value, a) for a in args)
    if hint is type(None):
        return value is None
    if origin is tuple:
        if not isinstance(value, tuple):
            return False
        if len(args) == 2 and args[1] is Ellipsis:
            return all(matches(v, args[0]) for v in value)
        return len(args) == len(value) and all(matches(v, a) for v, a in zip(value, args, strict=False))
    if origin is not None:  # Mapping[...], dict[...]
        return isinstance(value, origin)
    if hint is float:
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    if hint is int:
        return isinstance(value, int) and not isinstance(value, bool)
    return isinstance(value, hint)


def type_name(hint: Any) -> str:
    return getattr(hint, "__name__", None) or str(hint).replace("typing.", "")
