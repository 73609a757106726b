"""Stopping the worker processes a command started, wherever it started them (the console script's signal handling,
graftcache.cli.signals; a rollout's team, graftcache.rollout.workers): SIGTERM to each, SIGKILL to any still alive
WORKER_GRACE_S later, so no worker outlives its command. `Terminated` is SIGTERM raised as a KeyboardInterrupt, so
that the cleanup written for Ctrl-C runs for it too, in the command and in its workers alike. Workers are started
so that a stop reaches them through the command only (`sigint_ignored`) and none starts out of a stop's reach
(`sigterm_held`).
"""

from __future__ import annotations

import signal
import threading
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from multiprocessing.process import BaseProcess

WORKER_GRACE_S = 2.0  # how long stopped workers get to exit before SIGKILL


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised in the main thread: a KeyboardInterrupt so every cleanup written for Ctrl-C runs."""

    signum = signal.SIGTERM


def stop(processes: Sequence[BaseProcess]) -> None:
    """SIGTERM every live one of `processes`, then SIGKILL (and reap) those still alive WORKER_GRACE_S later.

    A stop raised while this runs (graftcache.cli.signals raises the command's stop again until the command has
    taken it) is held until every process is reaped, then raised: cut short, the SIGKILL would never come, and a
    worker that swallows SIGTERM (hf-libero's reset loop ends in `finally: continue`) would keep the command's exit
    waiting on it forever (multiprocessing joins its children at exit)."""
    held: KeyboardInterrupt | None = None
    alive = [p for p in processes if p.is_alive()]
    for process in alive:
        process.terminate()
    deadline = time.monotonic() + WORKER_GRACE_S
    for process in alive:
        while True:
            try:
                process.join(max(0.0, deadline - time.monotonic()))
                if process.is_alive():
                    process.kill()
                    process.join()
                break
            except KeyboardInterrupt as e:
                held = e
    if held is not None:
        raise held


@contextmanager
def sigint_ignored() -> Iterator[None]:
    """SIGINT ignored inside the block (in the main thread; elsewhere nothing changes): a worker process started here
    inherits it across exec, so a Ctrl-C at the terminal, which reaches the whole process group, stops the workers
    through the command only."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


@contextmanager
def sigterm_held() -> Iterator[None]:
    """A SIGTERM held while the block runs (one worker starting), then delivered: raised between a worker's spawn and
    the data it is then sent, the stop would leave a process that no stop reaches yet and that dies reading the rest,
    printing an EOFError traceback. A Python handler holds it, not the signal mask, which the process's other threads
    do not share."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    held: list[int] = []
    previous = signal.signal(signal.SIGTERM, lambda signum, frame: held.append(signum))
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)
        if held:
            signal.raise_signal(signal.SIGTERM)
