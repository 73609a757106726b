"""Process-level runtime settings: torch threads, devices and compute dtypes.

Why this exists: with torch on a 2-core machine, two intra-op threads in a data worker made a
256x256 to_tensor many times slower than one thread (docs/measured.md). Data workers therefore always run
single-threaded, while the main process keeps the cores for the model.

Why `auto` is the default compute dtype: bf16 autocast is faster than fp32 where the hardware computes bf16
(CUDA GPUs with bf16, x86 CPUs with AVX512-BF16 or AMX), and several times *slower* where torch emulates it
(docs/measured.md: MobileNetV2 on an AMD EPYC without AVX512-BF16). A default tuned to one CPU is wrong on the
next machine, so `auto` asks the hardware, and
only the resolved dtype (never "auto") is written into manifests, cache keys and results rows.
"""

from __future__ import annotations

import os
from collections.abc import Callable

import torch

from graftcache import MKL_CBWR
from graftcache.dtypes import AUTO, COMPUTE_DTYPES
from graftcache.errors import GraftcacheError

DTYPES: dict[str, torch.dtype] = {"fp16": torch.float16, "bf16": torch.bfloat16, "fp32": torch.float32}


def single_thread_worker(*_: object) -> None:
    """`worker_init_fn` for data-loading processes: one intra-op/inter-op thread, no OpenMP fan-out."""
    os.environ["OMP_NUM_THREADS"] = "1"
    torch.set_num_threads(1)


def granted_cpus() -> int:
    """The cores this process was given: OMP_NUM_THREADS where a scheduler set it (Ray sets it to a task's
    num_cpus, so two tasks on one node do not both take every core), else all of them."""
    granted = os.environ.get("OMP_NUM_THREADS", "")
    return int(granted) if granted.isdigit() and int(granted) > 0 else os.cpu_count() or 1


def set_main_threads(n: int | None = None) -> int:
    """Give the main (model) process `n` intra-op threads (default: the cores it was granted); returns the count.

    Several model processes on one machine (extract --shard, Ray tasks) must share the cores: with more threads
    than cores, torch's threads spin against each other (measured: 2 threads per process under load were 10x
    slower than 1)."""
    n = n or granted_cpus()
    torch.set_num_threads(n)
    return n


def resolve_device(name: str) -> torch.device:
    """`cpu`, `cuda` or `cuda:N`; asking for CUDA on a machine without it is an error, not a silent fallback."""
    try:
        dev = torch.device(name)
    except (RuntimeError, TypeError):
        raise GraftcacheError(f"--device {name!r}: expected cpu, cuda or cuda:N") from None
    if dev.type not in ("cpu", "cuda"):
        raise GraftcacheError(f"--device {name!r}: expected cpu, cuda or cuda:N")
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise GraftcacheError(f"--device {name}: CUDA is not available on this machine")
    return dev


#: Overrides what `auto` assumes of this CPU: "1" as if it computed bf16 in hardware, "0" as if it did not, unset
#: (or empty) to ask torch. Machines of one kind differ in CPU (some AMD EPYC have AVX512-BF16, some only AVX2),
#: so this is how one machine reproduces the other family's `auto` (the tests of both resolutions, CI on the
#: family it does not run on), and the way out where a hypervisor hides or fakes the flag.
CPU_BF16_ENV = "GRAFTCACHE_CPU_BF16"


def cpu_has_bf16() -> bool:
    """Whether this CPU computes bf16 in hardware (x86 AVX512-BF16 or AMX tiles), as torch reports it, unless
    $GRAFTCACHE_CPU_BF16 says otherwise."""
    forced = os.environ.get(CPU_BF16_ENV, "")
    if forced:
        if forced not in ("0", "1"):
            raise GraftcacheError(f"${CPU_BF16_ENV}={forced!r}: expected 1 (bf16 in hardware), 0 (none) or unset")
        return forced == "1"
    return cpu_bf16_unit() is not None


#: The CPU's bf16 units oneDNN computes on, the first found wins -> torch's probe of it (absent in older torch).
BF16_UNITS: dict[str, str] = {"amx": "_is_amx_tile_supported", "avx512_bf16": "_is_avx512_bf16_supported"}


def cpu_bf16_unit() -> str | None:
    """The bf16 unit of this CPU (a BF16_UNITS name) as torch reports it; None where torch finds none."""
    return next((unit for unit, probe in BF16_UNITS.items() if getattr(torch.cpu, probe, lambda: False)()), None)


def cuda_has_bf16(device: torch.device) -> bool:
    return torch.cuda.is_available() and torch.cuda.is_bf16_supported(including_emulation=False)


#: How `auto` is decided per device type: True -> bf16, False -> fp32.
HARDWARE_BF16: dict[str, Callable[[torch.device], bool]] = {
    "cpu": lambda _dev: cpu_has_bf16(),
    "cuda": cuda_has_bf16,
}


def resolve_compute_dtype(name: str, device: torch.device | str) -> str:
    """`auto` -> "bf16" where `device` computes bf16 in hardware, else "fp32"; explicit names pass through.

    Returns the resolved *name*, the form recorded in manifests, keys and rows.
    """
    if name not in COMPUTE_DTYPES:
        raise GraftcacheError(f"compute dtype {name!r}: choose one of {', '.join(COMPUTE_DTYPES)}")
    if name != AUTO:
        return name
    dev = torch.device(device) if isinstance(device, str) else device
    return "bf16" if HARDWARE_BF16.get(dev.type, lambda _d: False)(dev) else "fp32"


def resolve_dtype(name: str) -> torch.dtype:
    """Map a resolved dtype name (fp16, bf16, fp32) to a torch dtype."""
    try:
        return DTYPES[name]
    except KeyError:
        raise GraftcacheError(f"unknown dtype {name!r}; choose one of {', '.join(DTYPES)}") from None


def autocast(device: torch.device, dtype: torch.dtype):
    """Autocast context for model compute: bf16/fp16 autocast on CUDA, bf16 on CPU, off for fp32.

    fp16 autocast on CPU is slow and poorly supported, so CPU compute in fp16 mode runs fp32 and
    only the stored features are fp16.
    """
    if dtype == torch.float32 or (device.type == "cpu" and dtype == torch.float16):
        return torch.autocast(device.type, enabled=False)
    return torch.autocast(device.type, dtype=dtype)


def kernels(device: torch.device) -> str:
    """Which kernels computed on `device`: what a run's numbers depend on beyond its cell and dtype, recorded in its
    row. On one set of kernels a run's scores are equal whatever the thread count; other kernels sum in another
    order (oneDNN's bf16 products on AMX tiles against those on AVX512-BF16 or AVX2), so their rows of one run_id
    differ (graftcache.results.same_result). On CPU: ATen's vector ISA, the bf16 unit oneDNN finds (`cpu_bf16_unit`),
    a oneDNN ISA cap and an MKL mode other than graftcache's where set; on CUDA the GPU's compute capability."""
    if device.type == "cuda":
        major, minor = torch.cuda.get_device_capability(device)
        return f"cuda:sm_{major}{minor}"
    parts = [torch.backends.cpu.get_cpu_capability().lower(), *filter(None, [cpu_bf16_unit()])]
    cap = os.environ.get("ONEDNN_MAX_CPU_ISA") or os.environ.get("DNNL_MAX_CPU_ISA")
    if cap:
        parts.append(f"onednn<={cap}")
    blas = os.environ.get("MKL_CBWR", "")
    if blas != MKL_CBWR:
        parts.append(f"mkl_cbwr={blas or 'unset'}")
    return "cpu:" + "+".join(parts)
