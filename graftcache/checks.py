"""Range rules for request fields, declared beside each request and checked in one place.

Requests (ExtractRequest, FitRequest, TinyTrainConfig, TileRequest) derive from `Checked` and declare a `RULES`
table; their construction and the sweep recipe reader (`cls.check(overrides)`) both apply it, so a
count of 0 or a negative seed is a one-line error naming the field before any work starts, whichever
way the request was made.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any, ClassVar

from graftcache.errors import GraftcacheError

Rule = tuple[Callable[[Any], bool], str]

POSITIVE: Rule = (lambda v: v > 0, "must be > 0")
NON_NEGATIVE: Rule = (lambda v: v >= 0, "must be >= 0")
FRACTION: Rule = (lambda v: 0 < v < 1, "must be between 0 and 1 (exclusive)")
SEEDS: Rule = (lambda v: len(v) > 0 and all(s >= 0 for s in v), "must list at least one seed, each >= 0")
EPISODES: Rule = (lambda v: len(v) > 0 and all(e >= 0 for e in v), "must list at least one episode index >= 0")
NAMES: Rule = (lambda v: len(v) > 0 and len(set(v)) == len(v), "must name at least one, each once")
SHARD: Rule = (lambda v: len(v) == 2 and 0 <= v[0] < v[1], "must be i/N with 0 <= i < N")


def check_fields(values: Mapping[str, Any], rules: Mapping[str, Rule]) -> None:
    """Raise GraftcacheError for the first value (None means 'default', never checked) that breaks its rule."""
    for name, (ok, text) in rules.items():
        value = values.get(name)
        if value is not None and not ok(value):
            raise GraftcacheError(f"{name} = {value!r} {text}")


class Checked:
    """Mixin for request dataclasses: `RULES` checked at construction and on a dict of overrides."""

    RULES: ClassVar[dict[str, Rule]] = {}

    def __post_init__(self) -> None:
        self.check(vars(self))

    @classmethod
    def check(cls, values: Mapping[str, Any]) -> None:
        check_fields(values, cls.RULES)
