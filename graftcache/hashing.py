"""sha256 in one place: of bytes, files, canonical JSON and tensors.

Every hash graftcache records (cache keys, run_ids, weights and dataset file hashes, block
checksums, tiny-checkpoint folders) is one of these; keeping them together keeps each hash's bytes
defined once, so a value recorded by an earlier version is reproduced exactly.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Iterable
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    import torch

READ_BLOCK = 1 << 20


def sha256_bytes(data: bytes | memoryview) -> str:
    return hashlib.sha256(data).hexdigest()


def sha256_file(path: str | Path) -> str:
    """sha256 of a file's bytes, read in 1 MiB blocks."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(READ_BLOCK):
            h.update(block)
    return h.hexdigest()


def sha256_json(value: Any, *, compact: bool = False) -> str:
    """sha256 of `value` as JSON with sorted keys (non-JSON values as str); `compact` drops the spaces
    after separators (cache keys were defined that way, run_ids and tiny folders with the default)."""
    separators = (",", ":") if compact else None
    return sha256_bytes(json.dumps(value, sort_keys=True, default=str, separators=separators).encode())


def sha256_tensors(tensors: Iterable[tuple[str, torch.Tensor]], *, header_end: str) -> str:
    """sha256 over (name, dtype, shape, raw bytes) of each tensor, in the given order; `header_end`
    closes each "name|dtype|shape" header (encoder weights used "\\n", policy weights "|")."""
    import torch  # here, not at the top: keys and run_ids are hashed without loading torch

    h = hashlib.sha256()
    for name, tensor in tensors:
        t = tensor.detach().to("cpu").contiguous()
        h.update(f"{name}|{t.dtype}|{tuple(t.shape)}{header_end}".encode())
        h.update(t.reshape(-1).view(torch.uint8).numpy())  # hashed in place: no copy of a 1 GB embedding
    return h.hexdigest()
