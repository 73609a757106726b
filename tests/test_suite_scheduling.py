"""devtools/scheduling.py and tests/helpers/scheduling.py: SVT-AV1 run as root leaves its thread real-time; the
test writers put it back, and a test that does not is failed by conftest.py. Each case runs in a thread of its own,
whose policy is its own, so this process's main thread (the one the guard watches) is never touched."""

from __future__ import annotations

import os
import threading
from collections.abc import Callable
from pathlib import Path

import av
import numpy as np
import pytest
from helpers.datasets import write_mp4
from helpers.scheduling import STARTED, check_scheduling

from devtools.scheduling import current, describe

ROOT = os.geteuid() == 0
FRAMES = np.zeros((4, 64, 64, 3), np.uint8)


def _in_thread(job: Callable[[], object]) -> object:
    """What `job` returns (or raises), run in a new thread."""
    out: dict[str, object] = {}

    def run() -> None:
        try:
            out["value"] = job()
        except BaseException as e:
            out["error"] = e

    thread = threading.Thread(target=run)
    thread.start()
    thread.join()
    if "error" in out:
        raise out["error"]  # type: ignore[misc]
    return out["value"]


def _encode_av1(path: Path) -> None:
    with av.open(str(path), "w") as out:
        stream = out.add_stream("libsvtav1", 10)
        stream.pix_fmt, stream.width, stream.height = "yuv420p", 64, 64
        for f in FRAMES:
            out.mux(stream.encode(av.VideoFrame.from_ndarray(f, format="rgb24")))
        out.mux(stream.encode())


@pytest.mark.skipif(not ROOT, reason="SVT-AV1 changes the policy only when run as root")
def test_svt_av1_as_root_leaves_its_thread_real_time_and_the_writers_put_it_back(tmp_path: Path) -> None:
    before = _in_thread(current)

    def bare() -> tuple[int, int]:
        _encode_av1(tmp_path / "bare.mp4")
        return current()

    def kept() -> tuple[int, int]:
        write_mp4(tmp_path / "kept.mp4", FRAMES, codec="libsvtav1")
        return current()

    assert _in_thread(bare) == (os.SCHED_FIFO, 99)  # the fact the helper exists for
    assert _in_thread(kept) == before == STARTED != (os.SCHED_FIFO, 99)
    assert (tmp_path / "kept.mp4").stat().st_size > 0


@pytest.mark.skipif(not ROOT, reason="only root may make a thread real-time")
def test_a_test_leaving_its_process_real_time_is_failed_and_put_back() -> None:
    def leaked() -> tuple[str, tuple[int, int]]:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
        with pytest.raises(AssertionError) as failed:
            check_scheduling("tests/x.py::test_y")
        return str(failed.value), current()

    message, after = _in_thread(leaked)
    assert message.startswith(f"tests/x.py::test_y left this test process at SCHED_FIFO priority 1 (it started at "
                              f"{describe(STARTED)})")
    assert after == STARTED != (os.SCHED_FIFO, 1)
