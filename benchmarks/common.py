"""What every benchmark prints about where it ran, and small timing helpers (imported by the scripts
in this folder, which run as `python benchmarks/bench_*.py`)."""

from __future__ import annotations

import os
import platform
import statistics
import time
from collections.abc import Callable
from pathlib import Path

DEFAULT_DATASET = Path(__file__).resolve().parents[1] / "data" / "libero_sample"


def machine() -> str:
    """Cores, CPU model, library versions and thread settings: ratios are only comparable within one."""
    import av
    import lerobot
    import torch

    model = next((ln.split(":", 1)[1].strip() for ln in Path("/proc/cpuinfo").read_text().splitlines()
                  if ln.startswith("model name")), platform.processor())
    return (f"{os.cpu_count()} cores, {model}; torch {torch.__version__} ({torch.get_num_threads()} threads), "
            f"av {av.__version__}, lerobot {lerobot.__version__}, "
            f"OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS', 'unset')}, load average {os.getloadavg()[0]:.2f}")


def warm_page_cache(root: Path) -> None:
    """Read every data/video file once so no side of a comparison pays cold-disk reads."""
    for f in root.rglob("*"):
        if f.is_file() and f.suffix in (".mp4", ".parquet"):
            f.read_bytes()


def median_seconds(fn: Callable[[], object], repeats: int, warmup: int = 1) -> float:
    """Median wall time of `fn()` over `repeats` calls after `warmup` untimed ones."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)
