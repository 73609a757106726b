"""Whether work fits the machine: memory and disk estimates, checked before the work starts.

A count that cannot fit (`extract --grids 100000x100000`, `fit --batch-size 100000`) would otherwise run
until the kernel kills the process or the disk fills, with no message. The commands estimate what the
work needs from its shapes and refuse in one line naming the estimate and the limit (`require`). The
estimates are lower bounds of the peak (what must be held at once, not every temporary), so a refusal is
certain to be right, and work just under the limit still runs.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path
from typing import Any

from graftcache.errors import GraftcacheError

#: cgroup v2 / v1 files giving a container's memory limit and use (absent outside containers).
_CGROUP_LIMITS = (
    ("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory.current"),
    ("/sys/fs/cgroup/memory/memory.limit_in_bytes", "/sys/fs/cgroup/memory/memory.usage_in_bytes"),
)


class BudgetError(GraftcacheError):
    """Work that cannot fit in this machine's memory or disk (names the estimate and the limit)."""


def size(n: float) -> str:
    """Bytes as a short human figure (1.5 GiB, 12.0 MiB, 3.2 PiB)."""
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if abs(n) < 1024:
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return f"{n:.1f} PiB"


def available_memory(device: Any = "cpu") -> tuple[int, str]:
    """(bytes a new allocation can take, where that figure comes from) on `device` (a torch.device or name).

    CUDA: the device's free memory plus what torch's allocator holds unused. CPU: the kernel's MemAvailable
    (psutil when installed, else /proc/meminfo or os.sysconf), capped by a container's cgroup limit."""
    if str(device).startswith("cuda"):
        import torch

        free, _ = torch.cuda.mem_get_info(device)
        spare = torch.cuda.memory_reserved(device) - torch.cuda.memory_allocated(device)
        return free + spare, f"free memory on {device}"
    have, what = _host_available()
    for limit_file, usage_file in _CGROUP_LIMITS:
        try:
            limit = Path(limit_file).read_text().strip()
            used = int(Path(usage_file).read_text())
        except (OSError, ValueError):
            continue
        if limit.isdigit() and int(limit) - used < have:
            return max(0, int(limit) - used), "memory left under this container's limit"
    return have, what


def _host_available() -> tuple[int, str]:
    try:
        import psutil
    except ImportError:
        pass
    else:
        return int(psutil.virtual_memory().available), "available memory"
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024, "available memory"
    except OSError:
        pass
    return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"), "free memory"


def free_disk(location: str | Path) -> tuple[int, int] | None:
    """(free, total) bytes of the file system that holds `location` (its nearest existing folder), or None for
    an object-store URL (no limit to know)."""
    if "://" in str(location):
        return None
    path = Path(location).absolute()
    while not path.exists() and path != path.parent:
        path = path.parent
    usage = shutil.disk_usage(path)
    return usage.free, usage.total


def require(what: str, need: int, have: int, limit: str, hint: str) -> None:
    """BudgetError `what needs about NEED; LIMIT is HAVE; HINT` when `need` exceeds `have`."""
    if need > have:
        raise BudgetError(f"{what} needs about {size(need)}, but {limit} is {size(have)}; {hint}")
