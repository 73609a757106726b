"""One home per setting: a request field declares its default, type, help, flag, choices, range rule and whether a
recipe may set it, in one place (`setting(...)` on the dataclass field, graftcache/requests.py).

Everything else is derived from that declaration:

- the CLI's flags (graftcache.cli.common.add_flags): name, default, help, choices, metavar, parser;
- the range and choice checks (`Checked`), applied when a request is built and on a recipe's sections;
- the sweep recipe's schema: which keys a settings section takes (`recipe_keys`) and their types (codecs.matches);
- the command line written into rows and reports (`write_flags`, graftcache.sweep.command_line).

Why not draccus (lerobot's config library, `--policy.type=...`): it would replace argparse with flags spelled
`--batch_size` and values as YAML (`--seeds "[0,2]"`), so every existing flag (`--batch-size`, `--seeds 3`,
`--seed 0-4`, `--no-progress`, `--shard 0/4`) and recipe would break; it has no subcommands, mutually exclusive
flags or positional arguments; it checks types but no ranges; and a malformed value is a DecodingError
traceback (`steps`: Couldn't parse 'abc' into an int), not a one-line usage error. Field metadata read by a
small argparse adapter keeps the CLI as it is and gives the one home the issue asks for.
"""

from __future__ import annotations

import dataclasses
import functools
import typing
import warnings
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

from graftcache.checks import Rule, number_problem, problem, storable_problem
from graftcache.codecs import Codec, codec_for, without_none
from graftcache.errors import Deprecation, GraftcacheError

KEY = "graftcache.setting"


@dataclass(frozen=True)
class Setting:
    """What a request field means outside Python. `help` may be a function, for text that lists what a heavy
    module registers (controls, suites): the CLI calls it only when help is printed."""

    help: str | Callable[[], str] = ""
    rule: Rule | None = None
    choices: tuple[str, ...] | Callable[[], tuple[str, ...]] | None = None  # a function: a registry's names
    flag: str | None = ""        # "" : --the-field-name; None: no flag (the command sets it itself)
    codec: Codec | None = None   # None: by the field's type (graftcache.codecs.BY_TYPE); bools are switches
    metavar: str | None = None
    shown: str | None = None     # the default as the help writes it (else the codec's text of it)
    positional: bool = False
    recipe: bool = True          # False: a sweep sets it from its product, never a recipe's settings section
    twin: Twin | None = None     # a second flag for the same field, exclusive with the first
    formerly: str | None = None  # the field's former name: its flag and recipe key still read, with a FutureWarning
    # What a fit's results make of it (FitRequest; graftcache.fit.plan.Cell, graftcache.results.SCHEMA):
    cell: Identity | None = None  # part of each cell's identity, hence of its run_id
    shared: bool = False          # the cells of one backbone pass share it (graftcache.fit.plan.Plan.pass_key)
    column: bool = False          # a results column of its name, typed from the field's type


@dataclass(frozen=True)
class Identity:
    """How a setting enters the identity of each cell (graftcache.fit.plan.Cell, hashed into its run_id).

    `when` says for which cells the request's value counts; the others hold the type's zero (0, 0.0), so that
    cells that do not use the setting do not differ by it: "always", "scheduled" (cells whose objective takes
    steps: graftcache.fit.objectives.Objective.scheduled) or "lora" (the lora control's cells). A setting added to
    cells after results.IDENTITY_VERSION names the results format that added it (`since`) and the value every earlier
    cell held (`before`): it is hashed only where it differs from that, so every earlier cell keeps its run_id, and
    rows of earlier formats read as holding it (graftcache.results.upgrade)."""

    when: str = "always"
    since: int | None = None
    before: Any = None


@dataclass(frozen=True)
class Twin:
    """Another spelling of a field's flag with its own codec (--seed LIST beside --seeds N|LIST); a command line
    is written with the twin, whose text is never ambiguous."""

    flag: str
    codec: Codec
    help: str
    metavar: str | None = None


def setting(default: Any = dataclasses.MISSING, *, default_factory: Any = dataclasses.MISSING, **meta: Any) -> Any:
    """A dataclass field with its Setting (keyword arguments of Setting)."""
    return dataclasses.field(default=default, default_factory=default_factory, metadata={KEY: Setting(**meta)})


@dataclass(frozen=True)
class Declared:
    """A field and its setting, resolved: type hint, codec, flag and default."""

    name: str
    hint: Any
    setting: Setting
    default: Any  # dataclasses.MISSING: required

    @property
    def flag(self) -> str | None:
        if self.setting.flag is None:
            return None
        if self.setting.flag:
            return self.setting.flag
        if self.is_switch and self.default is True:
            return f"--no-{self.name.replace('_', '-')}"
        return f"--{self.name.replace('_', '-')}"

    @property
    def is_switch(self) -> bool:
        return self.hint is bool

    @property
    def choices(self) -> tuple[str, ...] | None:
        choices = self.setting.choices
        return choices() if callable(choices) else choices

    @property
    def codec(self) -> Codec:
        return self.setting.codec or codec_for(self.hint)


@functools.cache
def declared(cls: type) -> dict[str, Declared]:
    """Every field of request class `cls` with its setting (a field without one gets the default Setting)."""
    hints = typing.get_type_hints(cls)
    out = {}
    for f in dataclasses.fields(cls):
        if f.default_factory is not dataclasses.MISSING:
            default = f.default_factory()
        else:
            default = f.default
        out[f.name] = Declared(f.name, hints[f.name], f.metadata.get(KEY, Setting()), default)
    return out


def default_of(cls: type, name: str) -> Any:
    """A field's default: its one home."""
    return declared(cls)[name].default


def flag_of(cls: type, name: str) -> str:
    """The flag that sets field `name` of `cls` (e.g. for an error message that says which flag to pass)."""
    flag = declared(cls)[name].flag
    if flag is None:
        raise KeyError(f"{cls.__name__}.{name} has no flag")
    return flag


def recipe_keys(cls: type) -> tuple[str, ...]:
    """The keys a recipe's settings section for `cls` may set: every field not set by the sweep's product."""
    return tuple(name for name, d in declared(cls).items() if d.setting.recipe)


def renamed(cls: type, values: Mapping[str, Any], where: str) -> dict[str, Any]:
    """`values` (a recipe section) with each key that a field of `cls` was formerly called (its setting's
    `formerly`) under the field's name, after a FutureWarning naming the place and the new key: recipes written
    before a rename still read. Both spellings at once is an error naming them."""
    former = {d.setting.formerly: name for name, d in declared(cls).items() if d.setting.formerly}
    out: dict[str, Any] = {}
    for key, value in values.items():
        name = former.get(key, key)
        if name in out:
            raise GraftcacheError(f"{where}: {key} and {name} are one setting ({name}); keep {name} only")
        if name != key:
            warnings.warn(f"{where}: {key} is now called {name}; rename it, the old key is deprecated",
                          Deprecation, stacklevel=2)
        out[name] = value
    return out


def value_problem(d: Declared, value: Any) -> str | None:
    """Why `value` breaks field `d`'s choices or rule (one phrase), or None. A number must also be what every
    numeric setting must be, so that downstream code and the column recording it can take it: an integer or a
    finite float before its rule judges it (graftcache.checks.number_problem), an int64 after
    (storable_problem: a field's own rule, e.g. a seed's range, says more)."""
    choices = d.choices
    if choices is not None and value not in choices:
        return f"is not one of {', '.join(choices)}"
    kind = without_none(d.hint)
    numeric = kind in (int, float)
    return ((numeric and number_problem(kind, value))
            or (problem(d.setting.rule, value) if d.setting.rule is not None else None)
            or (numeric and storable_problem(kind, value)) or None)


def write_flags(cls: type, values: Mapping[str, Any]) -> list[str]:
    """`values` (fields of `cls`) as the flags that set them, each written by its codec, in the order given:
    a switch when it differs from its default, a value unless None. Names that are not fields of `cls` are the
    command's own plain flags, written `--name value`."""
    fields = declared(cls)
    parts: list[str] = []
    for name, value in values.items():
        d = fields.get(name)
        if d is None:
            if value is not None:
                parts.append(f"--{name.replace('_', '-')} {value}")
            continue
        if d.flag is None or value is None:
            continue
        if d.is_switch:
            if value != d.default:
                parts.append(d.flag)
            continue
        flag, codec = (d.setting.twin.flag, d.setting.twin.codec) if d.setting.twin else (d.flag, d.codec)
        parts.append(f"{flag} {codec.write(value)}")
    return parts


class Checked:
    """Mixin for request dataclasses: every field's choices and rule, checked at construction and on a dict of
    overrides (a recipe's section), so a count of 0 or a negative seed is a one-line error naming the field before
    any work starts, whichever way the request was made."""

    def __post_init__(self) -> None:
        self.check(vars(self))

    @classmethod
    def check(cls, values: Mapping[str, Any]) -> None:
        """Raise GraftcacheError for the first value (None means 'default', never checked) that breaks its rule."""
        for name, d in declared(cls).items():
            value = values.get(name)
            if value is None:
                continue
            why = value_problem(d, value)
            if why:
                raise GraftcacheError(f"{name} = {shown(value)} {why}")


def shown(value: Any, width: int = 80) -> str:
    """repr of a value, cut to `width` characters: a list of a million seeds stays one short line."""
    if isinstance(value, tuple) and len(value) > 8:
        return f"({', '.join(map(repr, value[:8]))}, ... {len(value)} in all)"
    text = repr(value)
    return text if len(text) <= width else f"{text[:width - 5]} ...{text[-1]}"
