"""A lock file that processes on any number of machines may contend for: a lease created with O_EXCL.

Results files (graftcache.results) take one around every append, and `fit` one per cell it computes, so that
two processes never both compute a cell. Both may live on a shared file system, which decides the primitive:

- fcntl/flock locks do not hold there reliably: Linux emulates flock on NFS with byte-range locks, which need
  a working lock manager (NLM, or NFSv4 state); a `nolock` mount, or a FUSE/SMB share, grants them locally,
  so two machines would both "hold" the lock and rows would be lost silently.
- `open(O_CREAT | O_EXCL)` is atomic on local file systems and NFSv3+ (the server creates exclusively): of two
  processes creating the same lock file, exactly one succeeds, on any machine.

The file holds {owner, host, pid, since}. Its holder dies without removing it, so a lease goes stale: at once
when its host is this one and its pid is gone, else when its heartbeat (the holder touches the file's mtime
every LEASE_S / 3 from a thread) has not moved for LEASE_S seconds of the *waiter's* clock (the mtime
is only compared with itself, never with a clock of another machine). A stale file is renamed away and
checked to be the one judged stale before it is deleted; a live lease taken by mistake (two waiters breaking
at once) is linked back. A holder checks `holds()` before it publishes, so one presumed dead (a frozen
process) and then taken over does not overwrite its successor.
"""

from __future__ import annotations

import json
import os
import random
import socket
import threading
import time
import uuid
from collections.abc import Callable
from pathlib import Path

from graftcache.store.lease import lease_seconds

#: first wait between tries; doubles up to MAX_POLL_S (a results append holds the lease briefly: docs/measured.md)
POLL_S = 0.005
MAX_POLL_S = 0.1


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's live process
        return True
    return True


class FileLease:
    """An exclusive lease on `path` (a file beside what it guards). Use as a context manager (waits) or with
    `try_acquire` / `release`; one object per lease attempt (it remembers the heartbeats it has seen)."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.host = socket.gethostname()
        self.owner = f"{self.host}:{os.getpid()}:{uuid.uuid4().hex[:12]}"
        self._seen: tuple[tuple[int, int, int], float] | None = None  # ((ino, mtime_ns, size), first seen)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    # ------------------------------------------------------------------ reading the current holder
    def record(self) -> dict | None:
        """The holder's record; {} while it is being written or unreadable, None without a lease file."""
        try:
            raw = self.path.read_bytes()
        except FileNotFoundError:
            return None
        try:
            return json.loads(raw)
        except ValueError:
            return {}

    def holder(self) -> str:
        """The holder as a user reads it: `host pid N since HH:MM:SS`, or what the lease file says of none."""
        rec = self.record()
        if rec is None:
            return "no one (the lock file is gone)"
        if not rec:
            return "no one it names (an empty or unreadable lock file, being written or left by a killed process)"
        since = time.strftime("%H:%M:%S", time.localtime(rec["since"])) if "since" in rec else "?"
        return f"{rec.get('host', '?')} pid {rec.get('pid', '?')} since {since}"

    def holds(self) -> bool:
        """Whether this object's lease is still the file on disk (not released, not taken over)."""
        return (self.record() or {}).get("owner") == self.owner

    def _stale(self) -> bytes | None:
        """The lease file's bytes if its holder is dead (see the module docstring), else None."""
        try:
            st = os.stat(self.path)
            raw = self.path.read_bytes()
        except FileNotFoundError:
            return None
        try:
            rec = json.loads(raw)
        except ValueError:
            rec = {}
        if rec.get("host") == self.host and isinstance(rec.get("pid"), int) and not _pid_alive(rec["pid"]):
            return raw
        beat, now = (st.st_ino, st.st_mtime_ns, st.st_size), time.monotonic()
        if self._seen is None or self._seen[0] != beat:
            self._seen = (beat, now)
            return None
        return raw if now - self._seen[1] > lease_seconds() else None

    def _break(self, judged: bytes) -> None:
        """Remove the lease file judged stale (`judged`: its bytes then): renamed away first, so that of two
        processes breaking it one does, and put back if what was renamed is a newer holder's file."""
        grave = self.path.with_name(f"{self.path.name}.stale.{uuid.uuid4().hex[:12]}")
        try:
            os.rename(self.path, grave)
        except FileNotFoundError:
            return
        try:
            if grave.read_bytes() != judged:  # a new holder's file, created since we looked: give it back
                try:
                    os.link(grave, self.path)
                except FileExistsError:
                    pass
        finally:
            grave.unlink(missing_ok=True)
        self._seen = None

    # ------------------------------------------------------------------ taking and giving back
    def try_acquire(self) -> bool:
        """Take the lease if it is free or stale; False while another process holds it."""
        for _ in range(3):  # once more after breaking a stale lease, or after the folder was removed meanwhile
            self.path.parent.mkdir(parents=True, exist_ok=True)
            try:
                fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
            except FileNotFoundError:  # its folder removed by a process that left it empty (results claims)
                continue
            except FileExistsError:
                judged = self._stale()
                if judged is None:
                    return False
                self._break(judged)
                continue
            try:
                try:
                    os.write(fd, json.dumps({"owner": self.owner, "host": self.host, "pid": os.getpid(),
                                             "since": time.time()}).encode())
                finally:
                    os.close(fd)
                self._stop.clear()
                self._thread = threading.Thread(target=self._heartbeat, daemon=True, name=f"lease {self.path.name}")
                self._thread.start()
            except BaseException:  # Ctrl-C or SIGTERM before the caller knows it holds the lease: not left behind
                self._stop.set()
                self.path.unlink(missing_ok=True)
                raise
            return True
        return False

    def acquire(self, on_wait: Callable[[str], None] | None = None, patience: float = 0.0) -> None:
        """Wait until the lease is ours; `on_wait(holder)` is called once if another process holds it for
        longer than `patience` seconds."""
        delay, told, start = POLL_S, False, time.monotonic()
        while not self.try_acquire():
            if not told and on_wait is not None and time.monotonic() - start >= patience:
                on_wait(self.holder())
                told = True
            time.sleep(delay * random.uniform(0.5, 1.5))  # jittered: waiters do not retry in lockstep
            delay = min(2 * delay, MAX_POLL_S)

    def _heartbeat(self) -> None:
        while not self._stop.wait(lease_seconds() / 3):
            if not self.holds():
                return
            try:
                os.utime(self.path)
            except OSError:
                return

    def release(self) -> None:
        """Give the lease back (a lease taken over by another process is left to it)."""
        self._stop.set()
        try:
            if self._thread is not None:
                self._thread.join()
        finally:  # the lease file goes even when Ctrl-C or SIGTERM lands in the join
            self._thread = None
            if self.holds():
                self.path.unlink(missing_ok=True)

    def __enter__(self) -> FileLease:
        self.acquire()
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()
