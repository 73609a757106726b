"""Dtype names as plain data (no torch): the choices of --compute-dtype and extract's --storage-dtype, read by the
requests and the CLI's parser without importing torch. graftcache.runtime maps them to torch dtypes, and
graftcache.store.cache.STORAGE_DTYPES the stored ones to numpy dtypes.
"""

from __future__ import annotations

AUTO = "auto"
#: What a model computes in; auto resolves per device (graftcache.runtime.resolve_compute_dtype).
COMPUTE_DTYPES = (AUTO, "bf16", "fp32")
#: What a cache may store features as.
STORED_DTYPES = ("fp16", "bf16", "fp32")
