"""The probe harness: run one command as a skeptical user would and check how it ends.

A probe runs in this process (`graftcache.cli.main(argv)`, output captured with capsys) unless the process boundary
is the thing tested (signals, interrupts, worker processes): then `start_process` starts `python -m graftcache`
and `finish` waits for it.
Either way it returns an `Outcome`, and `assert_one_line_error` / `assert_succeeded` check what every probe
asserts: the exit code, no traceback, the named places in the last line. `Snapshot` checks that nothing outside
the folders a command may write changed.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import pytest

from graftcache.cli import main
from graftcache.store.cache import PROGRESS_DIR


@dataclass(frozen=True)
class Outcome:
    """How a command ended: its exit code and what it printed."""

    code: int
    out: str
    err: str

    @property
    def last(self) -> str:
        """The last line on stderr: where a failure's one line is."""
        lines = self.err.strip().splitlines()
        return lines[-1] if lines else ""


def run_cli(argv: Sequence[str], capsys: pytest.CaptureFixture) -> Outcome:
    """The command in this process; argparse's usage error (SystemExit) is its exit code, as in a shell."""
    capsys.readouterr()
    try:
        code = main([str(a) for a in argv])
    except SystemExit as e:
        code = e.code if isinstance(e.code, int) else 1
    captured = capsys.readouterr()
    return Outcome(code, captured.out, captured.err)


def start_process(argv: Sequence[str], env: dict[str, str] | None = None, prelude: str = "") -> subprocess.Popen:
    """`python -m graftcache ARGV` with this test's environment (PYTHONPATH: the graftcache under test).
    `prelude`: Python run first in the child, e.g. a patch that slows a step down so a signal lands mid-way."""
    path = os.pathsep.join([str(Path(__file__).resolve().parents[2]), os.environ.get("PYTHONPATH", "")])
    code = ["-m", "graftcache"] if not prelude else \
        ["-c", f"{prelude}\nimport sys\nfrom graftcache.cli import main\nsys.exit(main())"]
    return subprocess.Popen([sys.executable, *code, *map(str, argv)], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, env={**os.environ, "PYTHONPATH": path, **(env or {})})


def hang_after_blocks(kept: int) -> str:
    """A `start_process` prelude: the extraction writes its first `kept` blocks, then its writer waits forever before
    the next one, so a SIGKILL sent once `kept` block markers exist lands at a known point (no race with a fast
    writer on a loaded machine)."""
    return f"""
import threading, graftcache.store.cache as c
write, calls = c.FeatureCache.write_block, []
def write_then_hang(self, block, data):
    calls.append(block)
    if len(calls) > {kept}:
        threading.Event().wait()
    write(self, block, data)
c.FeatureCache.write_block = write_then_hang
"""


def wait_for(ready: Callable[[], bool], proc: subprocess.Popen, what: str, timeout: float = 300) -> None:
    """Poll `ready` until it holds; fails, naming `what`, if `proc` ends first or `timeout` seconds pass."""
    deadline = time.monotonic() + timeout
    while not ready():
        assert proc.poll() is None, f"ended before {what}: {finish(proc).err[-3000:]}"
        assert time.monotonic() < deadline, f"no {what} within {timeout} s"
        time.sleep(0.02)


def kill_after_blocks(proc: subprocess.Popen, root: Path, kept: int) -> Outcome:
    """SIGKILL `proc` (started with `hang_after_blocks(kept)`) once the cache under the cache root `root` holds
    `kept` block markers; its outcome."""
    wait_for(lambda: len(list(root.glob(f"*/{PROGRESS_DIR}/block-*.json"))) >= kept, proc, f"{kept} written blocks")
    proc.send_signal(signal.SIGKILL)
    return finish(proc)


def children(pid: int) -> list[int]:
    """The live child processes of `pid` (worker processes), from /proc."""
    found = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid and fields[0] != "Z":
            found.append(int(stat.parent.name))
    return found


def alive(pids: Sequence[int]) -> list[int]:
    """Those of `pids` still running (not exited, not a zombie)."""
    out = []
    for pid in pids:
        try:
            state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
        except OSError:
            continue
        if state != "Z":
            out.append(pid)
    return out


def finish(proc: subprocess.Popen, timeout: float = 600) -> Outcome:
    out, err = proc.communicate(timeout=timeout)
    return Outcome(proc.returncode, out, err)


def assert_one_line_error(outcome: Outcome, names: Sequence[str] = (), code: int | None = None) -> None:
    """A non-zero exit (or exactly `code`), no traceback, and a last line from graftcache or argparse holding
    every text of `names`."""
    assert outcome.code != 0 if code is None else outcome.code == code, (outcome.code, outcome.err[-3000:])
    assert "Traceback" not in outcome.err + outcome.out, outcome.err[-3000:]
    assert outcome.last.startswith(("graftcache", "usage")), outcome.err[-3000:]
    for text in names:
        assert text in outcome.last, f"{text!r} not in {outcome.last!r}"


def assert_succeeded(outcome: Outcome) -> None:
    assert outcome.code == 0 and "Traceback" not in outcome.err, outcome.err[-3000:]


@dataclass(frozen=True)
class Snapshot:
    """Every file and link under a folder, with its size and modification time."""

    files: dict[str, tuple[int, int]]

    @classmethod
    def of(cls, folder: Path) -> Snapshot:
        return cls({p.relative_to(folder).as_posix(): (p.lstat().st_size, p.lstat().st_mtime_ns)
                    for p in folder.rglob("*") if not p.is_dir() or p.is_symlink()})

    def assert_unchanged(self, folder: Path) -> None:
        now = Snapshot.of(folder).files
        changed = sorted(k for k in self.files.keys() | now.keys() if self.files.get(k) != now.get(k))
        assert not changed, f"changed under {folder}: {changed[:10]}"
