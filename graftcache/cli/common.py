"""Flags built from the request dataclasses, and the few flags shared by commands that are not request fields.

A request field's setting (graftcache/requests.py, graftcache/settings.py) is the one home of its flag: name,
default, help, choices, metavar and parser all come from it (`add_flags`). Values are parsed by the field's codec
and checked by its rule here, at parse time, so a bad flag is argparse's one-line usage error before any work
starts (never a traceback from deep inside a run); the request is built from the parsed namespace by field name
(`request_from`), and checks the same rules again whichever way it is built.
"""

from __future__ import annotations

import argparse
import dataclasses
import warnings
from collections.abc import Callable
from typing import Any

from graftcache.codecs import BadText
from graftcache.errors import Deprecation
from graftcache.settings import Declared, declared, shown, value_problem


class LazyText(str):
    """Help text made only when help is printed: argparse %-formats every help text (and a description holding
    "%(prog)") when it prints them, and this text is made then. For help that lists what a heavy module registers
    (controls, suites), so that building the parser imports none of them."""

    make: Callable[[], str]

    def __new__(cls, make: Callable[[], str]) -> LazyText:
        text = super().__new__(cls, "%(prog)s")
        text.make = make
        return text

    def __mod__(self, params: Any) -> str:
        return self.make() % params


def _parser(d: Declared, codec: Any = None) -> Callable[[str], Any]:
    """argparse type: the text read by the field's codec, then checked by its rule (a one-line usage error)."""
    codec = codec or d.codec

    def parse(text: str) -> Any:
        value = codec.parse(text, d.setting.rule)
        why = value_problem(d, value)
        if why:
            raise BadText(f"{shown(value)} {why}")
        return value

    parse.__name__ = d.name  # argparse names the type in its own messages
    return parse


def _help(d: Declared, help: str | None) -> str | None:
    """The setting's help (or `help`) with the default, as the flag's codec writes it."""
    text = help if help is not None else d.setting.help
    if callable(text):
        make = text
        return LazyText(lambda: _with_default(d, make()))
    return _with_default(d, text) or None


def _with_default(d: Declared, text: str) -> str:
    if d.default is None or d.default is dataclasses.MISSING or d.is_switch:
        return text
    return f"{text} (default {d.setting.shown or d.codec.write(d.default)})".strip()


class _Former(argparse.Action):
    """A setting's former flag (its `formerly`): stores as the current flag does, after a FutureWarning that names
    the current one, so command lines written before a rename (recorded in rows, scripts) still parse."""

    def __init__(self, *args: Any, current: str, **kw: Any) -> None:
        super().__init__(*args, **kw)
        self.current = current

    def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace, values: Any,
                 option_string: str | None = None) -> None:
        warnings.warn(f"{option_string} is now {self.current}; the old flag is deprecated", Deprecation,
                      stacklevel=2)
        setattr(namespace, self.dest, values)


def add_flag(p: argparse.ArgumentParser | argparse._ActionsContainer, request: type, name: str, *,
             overrides: bool = False, help: str | None = None) -> None:
    """The flag (or positional argument) of field `name` of `request`, as its setting declares it. With
    `overrides` the flag overrides a value read elsewhere (a recipe): it is absent from the namespace unless given
    (see `given`). `help` replaces the setting's (a command whose flag means something narrower)."""
    d = declared(request)[name]
    if d.flag is None:
        raise ValueError(f"{request.__name__}.{name} has no flag")
    required = d.default is dataclasses.MISSING
    kw: dict[str, Any] = {"help": _help(d, help)}
    if d.setting.positional:
        p.add_argument(name, type=_parser(d), **kw)
        return
    kw["dest"] = name
    if required:
        kw["required"] = True
    else:
        kw["default"] = argparse.SUPPRESS if overrides else d.default
    if d.is_switch:
        p.add_argument(d.flag, action="store_false" if d.default is True else "store_true", **kw)
        return
    if d.choices is not None:
        kw["choices"] = d.choices
    else:
        kw["type"] = _parser(d)
        kw["metavar"] = d.setting.metavar or d.codec.metavar
    if d.setting.formerly:
        p.add_argument(f"--{d.setting.formerly.replace('_', '-')}", **{**kw, "help": argparse.SUPPRESS,
                       "default": argparse.SUPPRESS}, action=_Former, current=d.flag)
    twin = d.setting.twin
    if twin is None:
        p.add_argument(d.flag, **kw)
        return
    group = p.add_mutually_exclusive_group()
    group.add_argument(d.flag, **kw)
    group.add_argument(twin.flag, type=_parser(d, twin.codec), dest=name, metavar=twin.metavar, help=twin.help,
                       **({"default": argparse.SUPPRESS} if overrides else {}))


def add_flags(p: argparse.ArgumentParser, request: type, *, skip: tuple[str, ...] = (), overrides: bool = False,
              **helps: str) -> None:
    """A flag for every field of `request` that has one, in the fields' order, except `skip`; `helps` replace the
    help of the named fields."""
    for name, d in declared(request).items():
        if d.flag is not None and name not in skip:
            add_flag(p, request, name, overrides=overrides, help=helps.get(name))


def given(request: type, args: argparse.Namespace) -> dict[str, Any]:
    """The fields of `request` set on the command line by flags made with `overrides=True`."""
    return {n: v for n, v in vars(args).items() if n in declared(request)}


def request_from[R](request: type[R], args: argparse.Namespace, **values: Any) -> R:
    """The request whose fields with a flag are the namespace's values of the same name, then `values`. Fields
    without one (the command sets them: `values`, else their default) are never read from the namespace, where
    argparse's own entries may share their names: the subcommand's name is `command`, which FitRequest's field of
    that name took for the command line, so rows recorded `command = "fit"`."""
    names = {n for n, d in declared(request).items() if d.flag is not None} - set(values)
    return request(**{n: v for n, v in vars(args).items() if n in names}, **values)


def add_cache_flag(p: argparse.ArgumentParser) -> None:
    """--cache for commands that take no request (ls, info, verify, push, pull): the request's flag, as declared."""
    from graftcache.requests import ExtractRequest

    add_flag(p, ExtractRequest, "cache")
