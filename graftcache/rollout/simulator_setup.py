"""A process's set-up around the LIBERO simulator, wherever it runs one (this process, a team worker, a Ray actor):
the simulator's libraries checked before anything else (`require_simulator`), their set-up chatter sent to a debug
logger (`simulator_chatter`), lerobot's per-episode bar off where it would flood a log (`quiet_inner_bars`), and the
policy's torch threads fixed (`policy_threads`).

The simulator's libraries announce their set-up in every process, for every suite and env they build (robosuite's
macro-file warning at import, LIBERO's task-order line per suite, lerobot's env-building lines): twelve envs in a
team of workers made a quarter of a run's log. Those lines (CHATTER) go to the debug logger SIMULATOR_LOG instead,
filtered where every process (a team worker too) imports the simulator and builds its suites and envs
(`simulator_chatter`); any other line they print passes as it is.
"""

from __future__ import annotations

import importlib.util
import io
import logging
import multiprocessing
import re
import sys
import warnings
from collections.abc import Iterator
from contextlib import contextmanager, redirect_stdout
from typing import Any

from graftcache.errors import RolloutError
from graftcache.rollout import seam

INSTALL = "run `make setup-libero` (scripts/setup.sh libero) to install it"
#: torch's intra-op threads while an episode's policy runs, whatever `rollout --workers` is: the rows of N workers are
#: those of one (a thread count may change a reduction's order, hence an action, hence the episode), and N workers
#: on N cores do not spin against each other. The cost is small: the env step, not the policy, takes most of an
#: episode (benchmarks/bench_rollout.py measures both).
POLICY_THREADS = 1
#: The simulator's set-up announcements (see the module docstring): robosuite's three macro-file lines, LIBERO's
#: task order, lerobot's create_envs lines.
CHATTER = re.compile(r"(No private macro file found!|It is recommended to use a private macro file|To setup, run: "
                     r"python \S*setup_macros\.py|\[info\] using task orders |Creating LIBERO envs \||Restricting to "
                     r"task_ids=|Built vec env \|)")
#: Where CHATTER goes, at debug level (shown only where a user configures logging to show it).
SIMULATOR_LOG = logging.getLogger("graftcache.simulator")
#: robosuite's own logger (robosuite.utils.log_utils.DefaultLogger), which its import warns through
ROBOSUITE_LOG = "robosuite_logs"


def _demoted(record: logging.LogRecord) -> bool:
    """A logger filter: a CHATTER record goes to SIMULATOR_LOG at debug level instead of robosuite's handlers."""
    message = record.getMessage()
    if CHATTER.match(message):
        SIMULATOR_LOG.debug(message)
        return False
    return True


class _ChatterFilter(io.TextIOBase):
    """A stdout writing each whole line to `out`, but CHATTER lines to SIMULATOR_LOG at debug level. It may outlive
    its block: a module imported inside it that binds sys.stdout keeps it (torch imports sympy.strategies.core, whose
    `from sys import stdout` runs then) until the interpreter's exit, when it is collected."""

    def __init__(self, out: Any) -> None:
        self.out, self.pending = out, ""

    @property
    def closed(self) -> bool:
        """Closed when `out` is: a stream that is collected flushes itself unless closed, and the filter collected at
        exit, after `out` (pytest's capture, say) was closed, would raise from that flush, printed as "Exception
        ignored"."""
        return bool(self.out.closed)

    def write(self, text: str) -> int:
        *lines, self.pending = (self.pending + text).split("\n")
        for line in lines:
            self._line(line, "\n")
        return len(text)

    def _line(self, line: str, end: str) -> None:
        if CHATTER.match(line):
            SIMULATOR_LOG.debug(line)
        else:
            self.out.write(line + end)

    def flush(self) -> None:
        if self.pending:
            self._line(self.pending, "")
            self.pending = ""
        self.out.flush()


@contextmanager
def simulator_chatter() -> Iterator[None]:
    """Inside the block, the simulator's CHATTER goes to SIMULATOR_LOG: robosuite's logger filtered (from then on:
    it warns once per process, at import), stdout's lines too."""
    logging.getLogger(ROBOSUITE_LOG).addFilter(_demoted)  # added once however often (Filterer skips a repeat)
    out = _ChatterFilter(sys.stdout)
    try:
        with redirect_stdout(out):
            yield
    finally:
        out.flush()


def require_simulator() -> None:
    """Refuse, in one line naming how to install it, an environment without lerobot's LIBERO env."""
    for module in ("libero", "robosuite", "mujoco"):
        if importlib.util.find_spec(module) is None:
            raise RolloutError(f"the LIBERO simulator is not installed (no Python module {module}); {INSTALL}")
    try:
        with warnings.catch_warnings(), simulator_chatter():  # robosuite's source has an invalid escape: a
            warnings.simplefilter("ignore", SyntaxWarning)  # SyntaxWarning where no .pyc is cached (uv installs none)
            import lerobot.envs.libero  # noqa: F401  (imports hf-libero, which prompts on stdin without its config)
    except EOFError:
        raise RolloutError("hf-libero asked for its config on stdin ($LIBERO_CONFIG_PATH/config.yaml, default "
                           f"~/.libero, is missing); {INSTALL}, which writes it") from None
    except ImportError as e:
        raise RolloutError(f"the LIBERO simulator cannot be imported ({e}); {INSTALL}") from None


@contextmanager
def quiet_inner_bars() -> Iterator[None]:
    """lerobot's rollout draws a bar of its own per episode; off a terminal (a log) it would write a redraw per step,
    so it is disabled there and the rollout's own sparse lines remain (graftcache.progress); in a team worker too
    (graftcache.rollout.workers), where N of them would fight over the rollout's own bar."""
    if sys.stderr.isatty() and multiprocessing.parent_process() is None:
        yield
        return
    with seam.inner_bars_off():
        yield


@contextmanager
def policy_threads() -> Iterator[None]:
    """torch at POLICY_THREADS intra-op threads inside the block, the process's own count again after it."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(POLICY_THREADS)
    try:
        yield
    finally:
        torch.set_num_threads(before)
