"""Encoding: uint8 frames -> the encoder in batches under the compute dtype -> every stored grid (pooled in fp32)
and extra, in the stored dtype."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import torch

from graftcache.pooling import format_grid, pool_grid
from graftcache.runtime import autocast
from graftcache.store.cache import to_storage


def encode_frames(encoder: Any, frames: np.ndarray, grids: Sequence[tuple[int, int]], *, batch_size: int,
                  device: torch.device, compute: torch.dtype, dtype: str) -> dict[str, np.ndarray]:
    """Encode uint8 frames [N,H,W,3] in batches; returns {grid name or extra name: stored array}."""
    outs: dict[str, list[np.ndarray]] = {}
    for s in range(0, len(frames), batch_size):
        x = torch.from_numpy(frames[s:s + batch_size]).to(device)
        with torch.inference_mode(), autocast(device, compute):
            grid, extras = encoder.forward_with_extras(encoder.preprocess(x))
        for g in grids:
            outs.setdefault(format_grid(g), []).append(to_storage(pool_grid(grid.float(), g), dtype))
        for name, tokens in extras.items():
            outs.setdefault(name, []).append(to_storage(tokens.float(), dtype))
    return {k: np.concatenate(v) for k, v in outs.items()}
