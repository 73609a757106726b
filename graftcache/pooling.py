"""Pool an encoder's patch grid to the token grid a backbone expects (8x8 SmolVLA, 16x16 pi0.5).

Adaptive average pooling keeps every encoder comparable at a fixed token count without learning
anything: when the native grid is a multiple of the target, each token is the exact mean of its
block of cells; pooling to a finer grid than the native one only repeats (or, for non-multiples,
blends neighbouring) cells and adds no information.
"""

from __future__ import annotations

import re

import torch
import torch.nn.functional as F

from graftcache.errors import GraftcacheError

_GRID = re.compile(r"^\s*(\d+)\s*x\s*(\d+)\s*$")


def pool_grid(grid: torch.Tensor, out: tuple[int, int]) -> torch.Tensor:
    """[B,H,W,C] -> [B, out_h*out_w, C], adaptive average pooling, tokens in row-major order."""
    if grid.ndim != 4:
        raise GraftcacheError(f"pool_grid expects a [B,H,W,C] grid, got shape {tuple(grid.shape)}")
    b, h, w, c = grid.shape
    oh, ow = out
    if (h, w) != (oh, ow):
        grid = F.adaptive_avg_pool2d(grid.permute(0, 3, 1, 2), (oh, ow)).permute(0, 2, 3, 1)
    return grid.reshape(b, oh * ow, c)


def parse_grids(text: str) -> list[tuple[int, int]]:
    """"8x8,16x16" -> [(8, 8), (16, 16)] (order kept, duplicates dropped)."""
    grids: list[tuple[int, int]] = []
    for part in text.split(","):
        m = _GRID.match(part)
        if not m or int(m[1]) < 1 or int(m[2]) < 1:
            raise GraftcacheError(f"grid {part.strip()!r} in {text!r}: expected HxW with positive sizes, "
                                  f"e.g. 8x8,16x16")
        g = (int(m[1]), int(m[2]))
        if g not in grids:
            grids.append(g)
    return grids


def parse_grid(name: str) -> tuple[int, int]:
    """"8x8" -> (8, 8), the inverse of `format_grid`."""
    (grid,) = parse_grids(name)
    return grid


def format_grid(grid: tuple[int, int]) -> str:
    """(8, 8) -> "8x8", the name of a pooled grid in the cache and in results."""
    return f"{grid[0]}x{grid[1]}"
