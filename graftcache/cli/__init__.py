"""The `graftcache` console script: one module per command, registered here (no if-chains).

Every command module exposes `add_parser(subparsers)` (which sets `func`) and returns an exit code; `func` finds
the command line it was given, as a shell would run it again, in `args.command_line` (what results rows record).
A GraftcacheError becomes one line on stderr and exit code 2; Ctrl-C (exit 130) and SIGTERM (exit 143), at any
moment, one line that says how to resume (graftcache.cli.signals).
"""

from __future__ import annotations

import argparse
import errno
import os
import shlex
import sys
import warnings
from collections.abc import Callable, Sequence
from importlib import import_module
from typing import TextIO

from graftcache import __version__

#: OSErrors that describe the user's machine (disk full, permissions, read-only file system), not a bug:
#: one line naming the file, like any other bad input.
ENVIRONMENT_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EACCES, errno.EPERM, errno.EROFS})

COMMANDS = ("extract", "caches", "transfer", "train_tiny", "fit", "sweep", "report", "demo", "merge_rows", "export",
            "rollout")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="graftcache",
        description="Test vision encoders on frozen VLA backbones from cached features.",
    )
    parser.add_argument("--version", action="version", version=f"graftcache {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in COMMANDS:
        import_module(f"graftcache.cli.{name}").add_parser(sub)
    return parser


def _one_line(shown: Callable[..., None]) -> Callable[..., None]:
    """`warnings.showwarning` printing a graftcache Deprecation as one line (the others as `shown` does): its place
    in argparse or the TOML reader tells a user nothing; the new spelling does."""
    from graftcache.errors import Deprecation

    def show(message: Warning | str, category: type[Warning], filename: str, lineno: int, file: TextIO | None = None,
             line: str | None = None) -> None:
        if issubclass(category, Deprecation):
            print(f"graftcache: warning: {message}", file=sys.stderr if file is None else file)
        else:
            shown(message, category, filename, lineno, file, line)
    return show


def main(argv: Sequence[str] | None = None) -> int:
    """Run one command. `argv` None: this is the process's own entry point (the console script,
    `python -m graftcache`), which also keeps signals to one line during interpreter teardown."""
    os.environ.setdefault("TOKENIZERS_PARALLELISM", "false")
    if argv is None:
        warnings.showwarning = _one_line(warnings.showwarning)
    from graftcache.cli.signals import STOP, describe, exit_code, settle_io, stoppable

    command, started = "", False
    with stoppable(whole_process=argv is None) as stops:
        try:  # from the first import on: Ctrl-C while torch is still loading is one line too
            args = build_parser().parse_args(argv)
            args.command_line = shlex.join(["graftcache", *(sys.argv[1:] if argv is None else argv)])
            command, started = f" {args.command}", True
            stops.command_started()
            return _run(args)
        except KeyboardInterrupt as stop:
            STOP.take()
            settle_io()  # nothing the command started may print after its last line
            then = ("; run the same command again to resume" if started
                    else " while starting; nothing was done")
            print(f"graftcache{command}: {describe(stop)}{then}", file=sys.stderr)
            return exit_code(stop)


def _run(args: argparse.Namespace) -> int:
    """The command's exit code; a GraftcacheError or an OSError about the user's machine is one line, exit 2."""
    from graftcache.errors import GraftcacheError

    try:
        return int(args.func(args) or 0)
    except GraftcacheError as e:
        print(f"graftcache {args.command}: error: {e}", file=sys.stderr)
        return 2
    except OSError as e:
        if e.errno not in ENVIRONMENT_ERRNOS:
            raise
        where = f" ({e.filename})" if e.filename else ""
        hint = "; free space and run the same command again to resume" if e.errno == errno.ENOSPC else ""
        print(f"graftcache {args.command}: error: {e.strerror}{where}{hint}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
