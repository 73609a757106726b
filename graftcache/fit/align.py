"""The `align` objective (beyond the paper): fit the projector in closed form.

Instead of back-propagating the policy's flow loss, regress the native tower's post-connector
tokens (cached by `graftcache extract --encoder <backbone>-native`) on the LayerNorm'd candidate
tokens at the same grid positions: ridge regression with a bias, solved from streamed sufficient
statistics (X^T X, X^T Y, sums) fed block by block from the cache, so memory is O(C^2 + C*D) whatever the
number of frames. The
projector then holds LN(weight=1, bias=0) -> Linear(W, b) and is scored with the same offline
action MSE as a `flow` fit. One linear solve replaces hundreds of backward passes through the LM.
"""

from __future__ import annotations

from collections.abc import Iterable

import torch
from torch import nn
from torch.nn import functional as F

from graftcache.errors import FitError
from graftcache.pooling import pool_grid

RIDGE_ALPHA = 1e-3
STREAM_ROWS = 4096


def _as_grid(tokens: torch.Tensor, grid: tuple[int, int]) -> torch.Tensor:
    """[N, T, D] tokens on a square grid -> pooled to `grid` (unchanged when T already matches)."""
    n, t, d = tokens.shape
    if t == grid[0] * grid[1]:
        return tokens
    side = int(round(t**0.5))
    if side * side != t:
        raise FitError(f"align: native tokens ({t}) are not a square grid; cannot pool to {grid}")
    return pool_grid(tokens.reshape(n, side, side, d), grid)


@torch.no_grad()
def fit_ridge(projector: nn.Module, pairs: Iterable[tuple[torch.Tensor, torch.Tensor]], grid: tuple[int, int],
              alpha: float = RIDGE_ALPHA) -> float:
    """Set `projector` (a GraftProjector) to the ridge solution; returns the train R^2.

    `pairs` streams (candidate features [n, T, C], native tokens [n, T', D]) of the same frames and camera, a
    block at a time (graftcache.fit.stream): only the statistics are kept.
    """
    c = projector.in_features
    d = projector.out_features
    xtx = torch.zeros(c, c, dtype=torch.float64)
    xty = torch.zeros(c, d, dtype=torch.float64)
    sx = torch.zeros(c, dtype=torch.float64)
    sy = torch.zeros(d, dtype=torch.float64)
    syy = torch.zeros((), dtype=torch.float64)
    n = 0
    for src, tgt in pairs:
        tgt = _as_grid(tgt.float(), grid)
        if tgt.shape[:2] != src.shape[:2]:
            raise FitError(f"align: candidate tokens {tuple(src.shape[:2])} and native tokens "
                           f"{tuple(tgt.shape[:2])} do not line up")
        x_all = src.reshape(-1, c)
        y_all = tgt.reshape(-1, d)
        for s in range(0, x_all.shape[0], STREAM_ROWS):
            # float32 products per block (2x the float64 GEMM speed; block sums of layer-normed rows agree
            # with float64 to ~1e-7), accumulated across blocks in float64
            x = F.layer_norm(x_all[s:s + STREAM_ROWS].float(), (c,))
            y = y_all[s:s + STREAM_ROWS].float()
            xtx += (x.T @ x).double()
            xty += (x.T @ y).double()
            sx += x.sum(0, dtype=torch.float64)
            sy += y.sum(0, dtype=torch.float64)
            syy += (y.double() * y.double()).sum()
            n += x.shape[0]
    if n == 0:
        raise FitError("align: no frames to fit")
    mx, my = sx / n, sy / n
    cxx = xtx - n * torch.outer(mx, mx)
    cxy = xty - n * torch.outer(mx, my)
    # ridge scaled to the features' mean variance; features that never vary (the zero-image control) have none, and
    # any positive ridge then gives what least squares means for them: W = 0, b = the mean target
    spread = torch.trace(cxx) / c
    lam = alpha * spread if spread > 0 else 1.0
    w = torch.linalg.solve(cxx + lam * torch.eye(c, dtype=torch.float64), cxy)  # [C, D]
    b = my - mx @ w
    projector.norm.weight.fill_(1.0)
    projector.norm.bias.zero_()
    projector.proj.weight.copy_(w.T.float())
    projector.proj.bias.copy_(b.float())
    sst = syy - n * (my * my).sum()
    # residual sum of squares: sst - 2 w.cxy + w.cxx.w, with cxx w = cxy - lam w at the ridge optimum
    rss = sst - (cxy * w).sum() - lam * (w * w).sum()
    return float(1.0 - rss / sst)
