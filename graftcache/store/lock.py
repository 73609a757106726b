"""An advisory file lock so that two extract processes never write the same key at once.

fcntl.flock is released by the kernel when the holder dies (even on SIGKILL), so a crashed run
never leaves a stale lock behind. Only writers take it: readers (ls, info, verify, fit) never create a file
in the root, so a root the user cannot write serves them.
"""

from __future__ import annotations

import errno
import fcntl
import os
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

from graftcache.errors import CacheError


class Held:
    """What `exclusive` yields: a kernel lock is never taken over while held, so `check` has nothing to do
    (an object-store lease's `check` does)."""

    def check(self) -> None:
        return None


@contextmanager
def exclusive(path: Path, *, wait: bool = True, on_wait: Callable[[str], None] | None = None) -> Iterator[Held]:
    """Hold an exclusive lock on `path` (created if absent). If busy: wait (calling `on_wait(pid)`)
    or raise CacheError naming the holder."""
    path.parent.mkdir(parents=True, exist_ok=True)
    try:  # O_NOFOLLOW: a lock file that is a link would have the pid written where it points
        fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW, 0o644)
    except OSError as e:
        if e.errno != errno.ELOOP:
            raise
        raise CacheError(f"{path} is a symbolic link; a lock file is never followed") from None
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = Path(path).read_text().strip() or "?"
            if not wait:
                raise CacheError(f"{path}: cache is being written by another process (pid {holder})") from None
            if on_wait is not None:
                on_wait(holder)
            fcntl.flock(fd, fcntl.LOCK_EX)
        os.ftruncate(fd, 0)
        os.write(fd, str(os.getpid()).encode())
        yield Held()
    finally:
        fcntl.flock(fd, fcntl.LOCK_UN)
        os.close(fd)
