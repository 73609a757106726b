"""The `graftcache` console script: one module per command, registered here (no if-chains).

Every command module exposes `add_parser(subparsers)` (which sets `func`) and returns an exit code.
A GraftcacheError becomes one line on stderr and exit code 2; Ctrl-C says how to resume.
"""

from __future__ import annotations

import argparse
import errno
import os
import sys
from collections.abc import Sequence
from importlib import import_module

from graftcache import __version__

#: OSErrors that describe the user's machine (disk full, permissions, read-only file system), not a bug:
#: one line naming the file, like any other bad input.
ENVIRONMENT_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EACCES, errno.EPERM, errno.EROFS})

COMMANDS = ("extract", "caches", "transfer", "train_tiny", "fit", "sweep", "report", "demo", "tile", "merge_rows")


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


def main(argv: Sequence[str] | None = None) -> int:
    os.environ.setdefault("TOKENIZERS_PARALLELISM", "false")
    from graftcache.errors import GraftcacheError

    args = build_parser().parse_args(argv)
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
    except KeyboardInterrupt:
        print(f"graftcache {args.command}: interrupted; run the same command again to resume", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
