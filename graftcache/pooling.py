"""Pool an encoder's patch grid to the token grid a backbone expects (8x8 SmolVLA, 16x16 pi0.5), and
name grids: "HxW", or UNPOOLED for the encoder's own patch grid.

Adaptive average pooling keeps every encoder comparable at a fixed token count without learning
anything: when the unpooled grid is a multiple of the target, each token is the exact mean of its
block of cells; pooling to a finer grid than the unpooled one only repeats (or, for non-multiples,
blends neighbouring) cells and adds no information. So a cache stores the encoder's own grid by default
(UNPOOLED) and stage 2 pools it to whatever grid a fit reads (graftcache.fit.data.read_grid).

The grid names are read by graftcache/requests.py, which stays free of torch: torch is imported where
pooling runs, not with this module.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from typing import TYPE_CHECKING

from graftcache.errors import GraftcacheError

if TYPE_CHECKING:
    import torch

_GRID = re.compile(r"^\s*(\d+)\s*x\s*(\d+)\s*$")
#: The grid name of the encoder's own patch grid (EncoderSpec.grid), stored unpooled: the default of
#: `extract --grids`. Resolved to the encoder's HxW (`resolve_grids`) before anything is keyed.
UNPOOLED = "unpooled"


def pool_grid(grid: torch.Tensor, out: tuple[int, int]) -> torch.Tensor:
    """[B,H,W,C] -> [B, out_h*out_w, C], adaptive average pooling, tokens in row-major order."""
    import torch.nn.functional as F

    if grid.ndim != 4:
        raise GraftcacheError(f"pool_grid expects a [B,H,W,C] grid, got shape {tuple(grid.shape)}")
    b, h, w, c = grid.shape
    oh, ow = out
    if (h, w) != (oh, ow):
        grid = F.adaptive_avg_pool2d(grid.permute(0, 3, 1, 2), (oh, ow)).permute(0, 2, 3, 1)
    return grid.reshape(b, oh * ow, c)


def _hxw(part: str) -> tuple[int, int] | None:
    """" 8x8" -> (8, 8); None unless positive H and W."""
    m = _GRID.match(part)
    return (int(m[1]), int(m[2])) if m and int(m[1]) > 0 and int(m[2]) > 0 else None


def parse_grids(text: str) -> list[tuple[int, int]]:
    """"8x8,16x16" -> [(8, 8), (16, 16)] (order kept, duplicates dropped)."""
    grids: list[tuple[int, int]] = []
    for part in text.split(","):
        g = _hxw(part)
        if g is None:
            raise GraftcacheError(f"grid {part.strip()!r} in {text!r}: expected HxW with positive sizes, "
                                  f"e.g. 8x8,16x16")
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


def grid_names(text: str) -> tuple[str, ...]:
    """"unpooled, 8x8,8x8" -> ("unpooled", "8x8"): the grids `extract --grids` names, normalised (order kept,
    duplicates dropped), UNPOOLED still unresolved; a malformed name is a GraftcacheError."""
    names: list[str] = []
    for part in text.split(","):
        g = _hxw(part)
        if g is None and part.strip() != UNPOOLED:
            raise GraftcacheError(f"grid {part.strip()!r} in {text!r}: expected {UNPOOLED} (the encoder's own patch "
                                  f"grid) or HxW with positive sizes, e.g. {UNPOOLED},4x4")
        names.append(UNPOOLED if g is None else format_grid(g))
    return tuple(dict.fromkeys(names))


def valid_grid_names(names: Sequence[str]) -> bool:
    """At least one entry, each a grid name (UNPOOLED or HxW): the rule of ExtractRequest.grids."""
    return bool(names) and all(isinstance(n, str) and (n.strip() == UNPOOLED or _hxw(n)) for n in names)


def resolve_grids(names: Sequence[str], unpooled: tuple[int, int]) -> list[tuple[int, int]]:
    """Grid names -> grids, UNPOOLED as the encoder's own grid `unpooled`, duplicates dropped (order kept):
    `unpooled` and the encoder's grid spelled out store the same arrays under the same cache key."""
    return list(dict.fromkeys(unpooled if n == UNPOOLED else parse_grid(n) for text in names for n in grid_names(text)))
