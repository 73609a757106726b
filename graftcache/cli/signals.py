"""How the console script stops when asked to: Ctrl-C (SIGINT) or SIGTERM, at any moment, ends in one line on
stderr and exit code 130 / 143 (128 + the signal), never a traceback and never a silent death.

SIGTERM is turned into `Terminated`, a KeyboardInterrupt raised in the main thread, so it unwinds through the
very code paths Ctrl-C already takes: an extraction's finished blocks and a fit's written rows stay, nothing
half-written is marked complete, and the same command run again resumes. Before unwinding, the worker processes
this process started (DataLoader readers and decoders, fork-server children for object-store roots) are sent
SIGTERM, so none outlives the command; forked workers get the default SIGTERM action back (`_reset_in_child`), so
they die at once instead of running this handler. While a whole process is still starting (importing torch) or
already tearing down, there is nothing to keep: a signal is one line and an immediate exit (`_exit_at_once`).

A stop must not be lost either: libraries the command runs swallow it now and then (hf-libero builds a task's env inside
bare `except: continue` loops, so a SIGTERM landing there was dropped and the rollout finished with exit 0). So the
stop, once raised, is raised again every REDELIVER_S_UNHANDLED until the command has taken it (`_Stop`): a swallowed
one is raised again in ordinary code, and one taken is never raised twice.

Zarr runs every store read and write as a coroutine on an event loop thread of its own, which it stops and closes
at exit. A signal that cuts the main thread off from one it is waiting for leaves it running there; closed under
it, the loop drops it and Python prints "coroutine '_runner' was never awaited" after the command's last line.
So before that line, the stopped command lets the IO it started finish (`settle_io`).
"""

from __future__ import annotations

import _thread
import multiprocessing
import os
import signal
import sys
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager, suppress
from types import FrameType
from typing import Any

from graftcache.processes import Terminated, stop

#: Exit code for each signal that stops a command: 128 + the signal number, the shell convention.
EXIT_CODES = {signal.SIGINT: 128 + signal.SIGINT, signal.SIGTERM: 128 + signal.SIGTERM}
STOPPED = {signal.SIGINT: "interrupted", signal.SIGTERM: "terminated (SIGTERM)"}  # what the one line says
REDELIVER_S = 0.01  # a signal lost in a finaliser is sent again this much later (`_redeliver`)
SETTLE_S = 10.0  # how long a stopped command waits for the store IO it started (`settle_io`)
REDELIVER_S_UNHANDLED = 0.5  # a stop the command has not taken by then is raised again (`_Stop`)


def exit_code(stop: KeyboardInterrupt) -> int:
    return EXIT_CODES[getattr(stop, "signum", signal.SIGINT)]


def describe(stop: KeyboardInterrupt) -> str:
    return STOPPED[getattr(stop, "signum", signal.SIGINT)]


def stop_workers() -> None:
    """Every live child process started through multiprocessing (DataLoader workers of any start method) stopped
    (graftcache.processes.stop): no worker outlives a stopped command."""
    stop(multiprocessing.active_children())


def settle_io() -> None:
    """Wait (up to SETTLE_S, then cancel) for the coroutines still running on zarr's IO loop: the reads and writes
    the interrupted command had started (see the module). A second signal meanwhile ends the wait."""
    sync = sys.modules.get("zarr.core.sync")
    loop = sync.loop[0] if sync is not None else None
    if loop is None or loop.is_closed() or not loop.is_running():
        return
    import asyncio

    async def drain() -> None:
        # queued behind every coroutine submitted before it, so each of them is a task by now
        started = asyncio.all_tasks() - {asyncio.current_task()}
        if started:
            _, late = await asyncio.wait(started, timeout=SETTLE_S)
            for task in late:
                task.cancel()
            if late:
                await asyncio.wait(late, timeout=1.0)

    with suppress(KeyboardInterrupt, TimeoutError):
        asyncio.run_coroutine_threadsafe(drain(), loop).result(SETTLE_S + 2.0)


class _Stop:
    """The stop of the running command: raised once a signal comes, raised again (the signal re-sent to this process
    every REDELIVER_S_UNHANDLED) until `taken`, then ignored: the command is already stopping."""

    def __init__(self) -> None:
        self.signum: int | None = None
        self.taken = False
        self.lock = threading.Lock()

    def reset(self) -> None:
        with self.lock:
            self.signum, self.taken = None, False

    def raise_stop(self, signum: int, frame: FrameType | None) -> None:
        """The handler of SIGINT and SIGTERM while the command runs."""
        if self.taken:
            return
        if signum == signal.SIGTERM:
            # torch's SIGCHLD handler would report the workers stopped below as a crash ("worker killed by signal")
            signal.signal(signal.SIGCHLD, signal.SIG_DFL)
            stop_workers()
        if self.signum is None:
            self.signum = signum
            threading.Thread(target=self._resend, daemon=True, name="graftcache-stop").start()
        raise Terminated() if signum == signal.SIGTERM else KeyboardInterrupt()

    def _resend(self) -> None:
        """Trip the signal's Python handler again, not the signal itself: a real signal every half second cut the
        file reads of MuJoCo's model compiler (EINTR), which started over each time and never finished."""
        while True:
            threading.Event().wait(REDELIVER_S_UNHANDLED)
            with self.lock:
                if self.taken or self.signum is None:
                    return
                _thread.interrupt_main(self.signum)

    def take(self) -> None:
        """The command has the stop (main's handler of KeyboardInterrupt): no more of it is raised."""
        with self.lock:
            self.taken = True


STOP = _Stop()


def _reset_in_child() -> None:
    """A forked worker inherits `STOP.raise_stop`; it must die of SIGTERM at once, as a worker without it would."""
    if signal.getsignal(signal.SIGTERM) == STOP.raise_stop:
        signal.signal(signal.SIGTERM, signal.SIG_DFL)


def _exit_at_once(when: str) -> Callable[[int, FrameType | None], None]:
    """A handler for the moments when there is nothing to keep (the console script still importing, or
    tearing down after the command): one line, then exit at once. Raising KeyboardInterrupt there could land
    in a weakref callback or a finaliser, where Python prints it as "Exception ignored" and carries on."""

    def handler(signum: int, frame: FrameType | None) -> None:
        os.write(2, f"graftcache: {STOPPED[signum]} {when}\n".encode())
        os._exit(EXIT_CODES[signum])

    return handler


def _redeliver(unraisable: Any) -> None:
    """sys.unraisablehook: a KeyboardInterrupt raised inside a finaliser or a weakref callback (as an import or
    the garbage collector runs them) would be printed as "Exception ignored" and lost; the signal is sent again
    a moment later (from a thread: sent from here, it would be raised inside this hook), so it is raised in
    ordinary code. Once a stop has come, any other one is debris of what the stop cut short (a simulator's render
    context whose __init__ it interrupted fails in its __del__, robosuite's MjRenderContext on a stopped rollout):
    not printed, since the command's one line must stay its last."""
    if isinstance(unraisable.exc_value, KeyboardInterrupt):
        signum = getattr(unraisable.exc_value, "signum", signal.SIGINT)
        threading.Timer(REDELIVER_S, os.kill, (os.getpid(), signum)).start()
    elif STOP.signum is None:
        sys.__unraisablehook__(unraisable)


class Stops:
    """The handlers of one command's run; `command_started` switches to those that unwind (see the module)."""

    def __init__(self, installs: bool) -> None:
        self.installs = installs

    def command_started(self) -> None:
        if self.installs:
            STOP.reset()
            signal.signal(signal.SIGINT, STOP.raise_stop)
            signal.signal(signal.SIGTERM, STOP.raise_stop)


_FORK_HOOK: list[bool] = []


@contextmanager
def stoppable(*, whole_process: bool) -> Iterator[Stops]:
    """Inside the block SIGINT raises KeyboardInterrupt and SIGTERM raises Terminated, except while a whole
    process (the console script) is still starting: then either is one line and an immediate exit. Afterwards a
    whole process keeps one line and the exit code for teardown; main called in-process (e.g. by tests) gets the
    previous handlers back. Outside the main thread nothing is installed: only the main thread may set handlers."""
    if threading.current_thread() is not threading.main_thread():
        yield Stops(installs=False)
        return
    if not _FORK_HOOK:
        os.register_at_fork(after_in_child=_reset_in_child)
        _FORK_HOOK.append(True)
    saved = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM, signal.SIGCHLD)}
    hook, sys.unraisablehook = sys.unraisablehook, _redeliver
    stops = Stops(installs=True)
    if whole_process:
        starting = _exit_at_once("while starting; nothing was done")
        signal.signal(signal.SIGINT, starting)
        signal.signal(signal.SIGTERM, starting)
    else:
        stops.command_started()
    try:
        yield stops
    finally:
        if whole_process:
            sys.stderr.flush()
            exiting = _exit_at_once("while exiting")
            signal.signal(signal.SIGINT, exiting)
            signal.signal(signal.SIGTERM, exiting)
        else:
            STOP.take()  # main called in-process: nothing of its stop may reach the caller
            for s, handler in saved.items():
                signal.signal(s, handler if handler is not None else signal.SIG_DFL)
            sys.unraisablehook = hook
