"""How the console script stops when asked to: Ctrl-C (SIGINT) or SIGTERM, at any moment, ends in one line on
stderr and exit code 130 / 143 (128 + the signal), never a traceback and never a silent death.

SIGTERM is turned into `Terminated`, a KeyboardInterrupt raised in the main thread, so it unwinds through the
very code paths Ctrl-C already takes: an extraction's finished blocks and a fit's written rows stay, nothing
half-written is marked complete, and the same command run again resumes. Before unwinding, the worker processes
this process started (DataLoader readers and decoders, fork-server children for object-store roots) are sent
SIGTERM, so none outlives the command; forked workers get the default SIGTERM action back (`_reset_in_child`), so
they die at once instead of running this handler.
"""

from __future__ import annotations

import multiprocessing
import os
import signal
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from types import FrameType

#: Exit code for each signal that stops a command: 128 + the signal number, the shell convention.
EXIT_CODES = {signal.SIGINT: 128 + signal.SIGINT, signal.SIGTERM: 128 + signal.SIGTERM}
WORKER_GRACE_S = 2.0  # how long stopped workers get to exit before SIGKILL


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised in the main thread: a KeyboardInterrupt so every cleanup written for Ctrl-C runs."""

    signum = signal.SIGTERM


def exit_code(stop: KeyboardInterrupt) -> int:
    return EXIT_CODES[getattr(stop, "signum", signal.SIGINT)]


def describe(stop: KeyboardInterrupt) -> str:
    return "terminated (SIGTERM)" if isinstance(stop, Terminated) else "interrupted"


def stop_workers() -> None:
    """SIGTERM every live child process started through multiprocessing (DataLoader workers of any start method),
    then SIGKILL those still alive after WORKER_GRACE_S: no worker outlives a stopped command."""
    children = multiprocessing.active_children()
    for child in children:
        child.terminate()
    for child in children:
        child.join(WORKER_GRACE_S)
        if child.is_alive():
            child.kill()


def _on_term(signum: int, frame: FrameType | None) -> None:
    # torch's SIGCHLD handler would report the workers stopped below as a crash ("worker killed by signal")
    signal.signal(signal.SIGCHLD, signal.SIG_DFL)
    stop_workers()
    raise Terminated()


def _reset_in_child() -> None:
    """A forked worker inherits `_on_term`; it must die of SIGTERM at once, as a worker without it would."""
    if signal.getsignal(signal.SIGTERM) is _on_term:
        signal.signal(signal.SIGTERM, signal.SIG_DFL)


def _on_exit_signal(signum: int, frame: FrameType | None) -> None:
    """After the command ended (interpreter teardown: joins, atexit hooks): one line, then exit at once."""
    os.write(2, f"graftcache: {signal.Signals(signum).name} while exiting\n".encode())
    os._exit(EXIT_CODES[signum])


_FORK_HOOK: list[bool] = []


@contextmanager
def stoppable(*, whole_process: bool) -> Iterator[None]:
    """SIGINT raises KeyboardInterrupt and SIGTERM raises Terminated inside the block. `whole_process` (the console
    script): afterwards a signal still gives one line and its exit code during teardown; otherwise (main called
    in-process, e.g. by tests) the previous handlers come back. Outside the main thread nothing is installed:
    only the main thread may set handlers."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    if not _FORK_HOOK:
        os.register_at_fork(after_in_child=_reset_in_child)
        _FORK_HOOK.append(True)
    saved = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM, signal.SIGCHLD)}
    signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.signal(signal.SIGTERM, _on_term)
    try:
        yield
    finally:
        if whole_process:
            sys.stderr.flush()
            for s in (signal.SIGINT, signal.SIGTERM):
                signal.signal(s, _on_exit_signal)
        else:
            for s, handler in saved.items():
                signal.signal(s, handler if handler is not None else signal.SIG_DFL)
