"""Range rules for request fields: each names its test and the phrase that says what is wrong.

A request field names its rule in its setting (graftcache.settings.setting(rule=...)); `Checked` applies it when
the request is built and to a recipe's sections, and the CLI when it parses the flag, so each range is declared once.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from numbers import Integral, Real
from typing import Any

#: The largest int any setting takes: rows record int settings in Int64 columns (graftcache.results.SCHEMA), and
#: manifests, cache keys and checkpoint records hold them as JSON ints read back as int64; a count past it could
#: not be held anyway.
MAX_INT = 2**63 - 1
#: The largest seed anything accepts: results store seeds as Int64 (graftcache.results.SCHEMA), and every RNG
#: a seed feeds takes it, with the small offsets the fits add (torch.manual_seed up to 2**64 - 1,
#: numpy.random.default_rng any non-negative int).
MAX_SEED = MAX_INT


@dataclass(frozen=True)
class IntList:
    """Rule of a list of distinct ints in 0..`high`, one to `most` of them (seeds, episode indices).

    Its bounds are readable, so the CLI can refuse a range such as 0-100000000000 before expanding it
    (graftcache.codecs.int_list) with the very bounds the request checks."""

    what: str
    high: int
    most: int

    def problem(self, values: Sequence[int]) -> str | None:
        """Why `values` breaks the rule (one phrase), or None."""
        if not values:
            return f"must list at least one {self.what}"
        if len(values) > self.most:
            return f"lists {len(values)} {self.what}s; at most {self.most}"
        seen: set[int] = set()
        for v in values:
            if isinstance(v, bool) or not isinstance(v, int) or not 0 <= v <= self.high:
                return f"has {self.what} {v!r}: each must be an integer in 0..{self.high}"
            if v in seen:
                return f"repeats {self.what} {v}: each must be listed once"
            seen.add(v)
        return None


#: (test, why): the phrase, or a function that makes it, when the text lists what is only known on use.
Rule = tuple[Callable[[Any], bool], str | Callable[[], str]] | IntList

POSITIVE: Rule = (lambda v: v > 0, "must be > 0")
NON_NEGATIVE: Rule = (lambda v: v >= 0, "must be >= 0")
FRACTION: Rule = (lambda v: 0 < v < 1, "must be between 0 and 1 (exclusive)")
SEED: Rule = (lambda v: 0 <= v <= MAX_SEED, f"must be in 0..{MAX_SEED} (results store seeds as Int64)")
#: A million fits is more than any machine runs; a million ints is still cheap to hold while checking.
SEEDS = IntList("seed", MAX_SEED, 1_000_000)
EPISODES = IntList("episode", 2**63 - 1, 10_000_000)
NAMES: Rule = (lambda v: len(v) > 0 and len(set(v)) == len(v), "must name at least one, each once")
SHARD: Rule = (lambda v: len(v) == 2 and 0 <= v[0] < v[1] <= MAX_INT, f"must be i/N with 0 <= i < N <= {MAX_INT}")


#: AdamW's learning rate: each step moves a weight by about lr, and lr x weight_decay <= 1 keeps its decoupled decay
#: (weights times 1 - lr x weight_decay) from flipping their sign; past these a fit diverges, its rows NaN.
LEARNING_RATE: Rule = (lambda v: 0 < v <= 1, "must be in (0, 1] (AdamW moves each weight by about lr a step)")
WEIGHT_DECAY: Rule = (lambda v: 0 <= v <= 1, "must be in [0, 1] (AdamW scales weights by 1 - lr x weight_decay)")
#: Worker processes: more than any machine's cores gain nothing, and each is a process started at once.
MAX_WORKERS = 1024
WORKERS: Rule = (lambda v: 0 <= v <= MAX_WORKERS, f"must be in 0..{MAX_WORKERS} (processes started at once)")


def number_problem(kind: type, value: Any) -> str | None:
    """Why `value` is no value of a numeric setting of type `kind` (int or float) for its own rule to judge: an
    int setting takes an integer (not a bool), a float one a finite number (one phrase), or None. The CLI's codecs
    and a recipe's types refuse most of these as text; this holds for a request built in Python too."""
    if isinstance(value, bool) or not isinstance(value, Integral if kind is int else Real):
        return f"must be {'an integer' if kind is int else 'a number'}"
    if kind is float and not math.isfinite(value):
        return "must be a finite number"
    return None


def storable_problem(kind: type, value: Any) -> str | None:
    """Why an int setting's `value`, within its own rule, still cannot be recorded (past Int64), or None."""
    if kind is int and not -MAX_INT - 1 <= value <= MAX_INT:
        return f"must be at most {MAX_INT} in size (rows and manifests store it as an int64)"
    return None


def problem(rule: Rule, value: Any) -> str | None:
    """Why `value` breaks `rule` (one phrase), or None."""
    if isinstance(rule, IntList):
        return rule.problem(value)
    ok, text = rule
    return None if ok(value) else text() if callable(text) else text
