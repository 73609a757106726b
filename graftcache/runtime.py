"""Process-level runtime settings: torch threads, devices and dtypes.

Why this exists: with torch 2.10 on a 2-core machine, two intra-op threads in a data worker made a
256x256 to_tensor 70x slower than one thread. Data workers therefore always run single-threaded,
while the main process keeps the cores for the model.
"""

from __future__ import annotations

import os

import torch

DTYPES: dict[str, torch.dtype] = {"fp16": torch.float16, "bf16": torch.bfloat16, "fp32": torch.float32}


def single_thread_worker(*_: object) -> None:
    """`worker_init_fn` for data-loading processes: one intra-op/inter-op thread, no OpenMP fan-out."""
    os.environ["OMP_NUM_THREADS"] = "1"
    torch.set_num_threads(1)


def set_main_threads(n: int | None = None) -> int:
    """Give the main (model) process `n` intra-op threads (default: all cores); returns the count used."""
    n = n or os.cpu_count() or 1
    torch.set_num_threads(n)
    return n


def resolve_device(name: str) -> torch.device:
    """`cpu`, `cuda` or `cuda:N`; asking for CUDA on a machine without it is an error, not a silent fallback."""
    dev = torch.device(name)
    if dev.type == "cuda" and not torch.cuda.is_available():
        from graftcache.errors import GraftcacheError

        raise GraftcacheError(f"--device {name}: CUDA is not available on this machine")
    return dev


def resolve_dtype(name: str) -> torch.dtype:
    """Map a CLI dtype name (fp16, bf16, fp32) to a torch dtype."""
    try:
        return DTYPES[name]
    except KeyError:
        from graftcache.errors import GraftcacheError

        raise GraftcacheError(f"unknown dtype {name!r}; choose one of {', '.join(DTYPES)}") from None


def autocast(device: torch.device, dtype: torch.dtype):
    """Autocast context for model compute: bf16/fp16 autocast on CUDA, bf16 on CPU, off for fp32.

    fp16 autocast on CPU is slow and poorly supported, so CPU compute in fp16 mode runs fp32 and
    only the stored features are fp16.
    """
    if dtype == torch.float32 or (device.type == "cpu" and dtype == torch.float16):
        return torch.autocast(device.type, enabled=False)
    return torch.autocast(device.type, dtype=dtype)
