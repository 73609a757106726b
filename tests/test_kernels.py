"""What a run's numbers depend on beyond its cell and dtype: the kernels that computed it (graftcache.runtime.kernels),
never the thread count, fp32 matrix products included (MKL's strict mode, set by importing graftcache first)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

import graftcache
from graftcache.runtime import kernels

CPU = torch.device("cpu")
#: An fp32 product of a shape MKL parallelises over its sum, then the row the kernels of this process give.
PRODUCT = """
import graftcache, torch
from graftcache.runtime import kernels
torch.manual_seed(0)
a, b = torch.randn(64, 960), torch.randn(960, 960)
out = {}
for t in (1, 2):
    torch.set_num_threads(t)
    out[t] = a @ b
print(torch.equal(out[1], out[2]), kernels(torch.device("cpu")))
"""


def _product(**env: str) -> list[str]:
    clean = {k: v for k, v in os.environ.items() if k != "MKL_CBWR"}  # this process's graftcache set it
    clean["PYTHONPATH"] = str(Path(graftcache.__file__).parents[1])
    done = subprocess.run([sys.executable, "-c", PRODUCT], env={**clean, **env}, capture_output=True, text=True,
                          check=True)
    return done.stdout.split()


def test_fp32_products_do_not_depend_on_the_thread_count() -> None:
    """graftcache imported before torch: MKL sums in the order of its strict mode on one thread as on two, and the
    kernels say nothing of MKL; a mode the user set is kept, and recorded."""
    assert _product() == ["True", kernels(CPU)]
    assert "mkl_cbwr" not in kernels(CPU)
    assert _product(MKL_CBWR="AUTO")[1].endswith("+mkl_cbwr=AUTO")


def test_kernels_name_the_vector_isa_the_bf16_unit_and_what_capped_them(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(torch.backends.cpu, "get_cpu_capability", lambda: "AVX2")
    units = {"_is_amx_tile_supported": False, "_is_avx512_bf16_supported": False}
    for name in units:
        monkeypatch.setattr(torch.cpu, name, lambda name=name: units[name])
    for cap in ("ONEDNN_MAX_CPU_ISA", "DNNL_MAX_CPU_ISA"):
        monkeypatch.delenv(cap, raising=False)
    monkeypatch.setenv("MKL_CBWR", graftcache.MKL_CBWR)
    assert kernels(CPU) == "cpu:avx2"
    units["_is_avx512_bf16_supported"] = True
    assert kernels(CPU) == "cpu:avx2+avx512_bf16"
    units["_is_amx_tile_supported"] = True  # AMX tiles are what oneDNN's bf16 products then run on
    assert kernels(CPU) == "cpu:avx2+amx"
    monkeypatch.setenv("ONEDNN_MAX_CPU_ISA", "AVX512_CORE_BF16")
    monkeypatch.delenv("MKL_CBWR")
    assert kernels(CPU) == "cpu:avx2+amx+onednn<=AVX512_CORE_BF16+mkl_cbwr=unset"
