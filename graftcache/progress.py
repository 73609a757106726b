"""Progress reporting that suits where the output goes.

On a terminal: a tqdm bar. On a pipe, a file or a CI log: a plain line every ~10% of the work with
rate and ETA, so a log holds a dozen lines per stage instead of hundreds of KB of carriage-return
redraws. The choice is made per call from `sys.stderr.isatty()`.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Iterable, Iterator
from typing import Any

from tqdm import tqdm

LOG_EVERY = 0.10  # fraction of the total between two log lines


def _duration(seconds: float) -> str:
    seconds = int(round(seconds))
    return f"{seconds // 3600}:{seconds // 60 % 60:02d}:{seconds % 60:02d}" if seconds >= 3600 else \
        f"{seconds // 60}:{seconds % 60:02d}"


class LogProgress:
    """The tqdm subset graftcache uses (update, set_postfix(_str), close, iteration, context manager),
    printing one line to stderr each time another ~10% of `total` is done, and one at the end."""

    def __init__(self, iterable: Iterable | None = None, *, total: float | None = None, desc: str = "",
                 unit: str = "it", stream: Any = None) -> None:
        self.iterable = iterable
        self.total = total if total is not None else (len(iterable) if hasattr(iterable, "__len__") else None)
        self.desc, self.unit, self.n = desc, unit, 0
        self.stream = stream or sys.stderr
        self.postfix = ""
        self.t0 = time.perf_counter()
        self._next = LOG_EVERY
        self._closed = False

    def __iter__(self) -> Iterator:
        for item in self.iterable or ():
            yield item
            self.update(1)
        self.close()

    def __enter__(self) -> LogProgress:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def set_postfix(self, **kw: object) -> None:
        self.postfix = ", ".join(f"{k}={v}" for k, v in kw.items())

    def set_postfix_str(self, text: str) -> None:
        self.postfix = text

    def update(self, n: float = 1) -> None:
        self.n += n
        if self.total and self.n / self.total >= self._next and self.n < self.total:
            self._line()
            while self._next <= self.n / self.total:
                self._next += LOG_EVERY

    def _line(self) -> None:
        elapsed = time.perf_counter() - self.t0
        rate = self.n / elapsed if elapsed > 0 else 0.0
        done = f"{self.n:g}/{self.total:g}" if self.total else f"{self.n:g}"
        pct = f" {100 * self.n / self.total:3.0f}%" if self.total else ""
        eta = (f", eta {_duration((self.total - self.n) / rate)}" if self.total and rate > 0 and self.n < self.total
               else "")
        extra = f" [{self.postfix}]" if self.postfix else ""
        print(f"{self.desc}:{pct} {done} {self.unit} in {_duration(elapsed)} ({rate:.3g} {self.unit}/s{eta}){extra}",
              file=self.stream, flush=True)

    def close(self) -> None:
        if not self._closed and self.n:
            self._line()
        self._closed = True


def progress[T](iterable: Iterable[T] | None = None, *, total: float | None = None, desc: str = "",
                unit: str = "it", enabled: bool = True, leave: bool = True) -> Any:
    """A tqdm bar on a terminal, a LogProgress on anything else; `enabled=False` prints nothing at all."""
    if enabled and sys.stderr.isatty():
        return tqdm(iterable, total=total, desc=desc, unit=unit, leave=leave, dynamic_ncols=True)
    if not enabled:
        return tqdm(iterable, total=total, disable=True)
    return LogProgress(iterable, total=total, desc=desc, unit=unit)


def write(text: str) -> None:
    """Print a line without breaking an active terminal bar."""
    tqdm.write(text)
