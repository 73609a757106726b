"""A `--workers` team's worker process (graftcache.rollout.workers starts it by spawn, `serve` its target): it builds
its simulator, runs each episode the rollout sends it, writes the episode's video and row
(graftcache.rollout.record.run_one) and sends back its report, until told to finish.

Stops: the terminal's SIGINT is ignored (the rollout's one line says the stop); SIGTERM, the rollout's stop, ends the
worker quietly, and whatever the stop cuts short in its libraries is not printed (`_terminated`). The worker dies with
the rollout (Linux PR_SET_PDEATHSIG, `_die_with`), so a kill -9 of it leaves none running.
"""

from __future__ import annotations

import ctypes
import os
import signal
import sys
import threading
from collections.abc import Callable
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

from graftcache.processes import Terminated
from graftcache.rollout.episodes import Simulator
from graftcache.rollout.record import run_one
from graftcache.rollout.schedule import one_line

PR_SET_PDEATHSIG = 1  # linux/prctl.h


def serve(conn: Connection, spawn: Callable[[], Simulator], rollouts: Path, command: str, parent: int) -> None:
    """A worker's life: build the simulator, then run each (row, episode) sent, write its video and row, and send
    its EpisodeReport, until None or the pipe's end. An error is reported as one
    line ("failed"; "broken": building the simulator) and ends the worker; a stop (SIGTERM, its parent's death) ends
    it quietly."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, _terminated)
    try:
        _die_with(parent)
        _thread_locked_bars()
        try:
            sim = spawn()
        except Exception as e:
            conn.send(("broken", one_line(e)))
            return
        try:
            while (job := conn.recv()) is not None:
                row, episode = job
                try:
                    report = run_one(sim, row, episode, rollouts, command)
                except Exception as e:
                    conn.send(("failed", one_line(e)))
                    return
                conn.send(("done", report))
        finally:
            close = getattr(sim, "close", None)
            if close is not None:
                close()
    except (KeyboardInterrupt, EOFError, OSError):  # stopped, or the rollout that started it is gone
        return
    finally:  # a stop while the interpreter exits has nothing left to unwind (it would print from an atexit hook)
        signal.signal(signal.SIGTERM, signal.SIG_DFL)


def _terminated(signum: int, frame: Any) -> None:
    """A stop: raised, and from now on nothing that it cuts short is printed. An object whose `__init__` it
    interrupts can fail in its `__del__` (robosuite's MjRenderContext), which Python would print as "Exception
    ignored in ..." on the terminal before the rollout's one line."""
    sys.unraisablehook = _dropped
    raise Terminated()


def _dropped(unraisable: Any) -> None:
    """sys.unraisablehook of a stopped worker: its debris is not printed (see `_terminated`)."""


def _thread_locked_bars() -> None:
    """tqdm's bars (lerobot's rollout loop opens one, disabled here) share a lock that is by default a
    multiprocessing semaphore, registered with the rollout's resource tracker: a worker killed by SIGKILL (a stop's
    escalation, its parent's death) never unregisters it, and the tracker warns of a "leaked semaphore" on the
    terminal after the rollout's last line. A worker draws no bar of another process: a thread lock serves."""
    from tqdm import tqdm

    tqdm.set_lock(threading.RLock())


def _die_with(parent: int) -> None:
    """SIGKILL to this worker when its parent dies (Linux), so a kill -9 of the rollout leaves no worker running:
    SIGKILL, since SIGTERM is lost where a library swallows what its handler raises (hf-libero's reset loop ends in
    `finally: continue`), and an orphan has no one left to escalate."""
    if sys.platform.startswith("linux"):
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGKILL)
    if os.getppid() != parent:  # died before the prctl
        raise Terminated()

