"""The Encoder module every builder returns: uint8 frames -> normalised pixels -> patch grid.

Preprocessing is batched tensor ops on the encoder's device (no PIL, no per-image loop): robot
frames are already framed, so they are resized straight to the model's input size (antialiased,
no crop). Subclasses only say how pixels become a grid (`_grid`); shape checks, no-grad and the
optional autocast live here once.
"""

from __future__ import annotations

import contextlib
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

from graftcache.encoders.spec import EncoderSpec
from graftcache.errors import EncoderError
from graftcache.runtime import autocast


class Encoder(nn.Module):
    """A frozen image encoder with a fixed input size and patch grid (see EncoderSpec)."""

    def __init__(self, spec: EncoderSpec, model: nn.Module, weights_info: dict[str, Any]) -> None:
        super().__init__()
        self.spec = spec
        self.model = model
        self.weights_info = weights_info
        self.compute_dtype: torch.dtype | None = None  # None: inherit the caller's autocast context
        self.register_buffer("mean", torch.tensor(spec.mean, dtype=torch.float32).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(spec.std, dtype=torch.float32).view(1, 3, 1, 1), persistent=False)

    @property
    def device(self) -> torch.device:
        return self.mean.device

    def preprocess(self, frames_u8: torch.Tensor) -> torch.Tensor:
        """[B,H,W,3] uint8 (any device) -> [B,3,S,S] float32 on the encoder's device, normalised."""
        if not isinstance(frames_u8, torch.Tensor) or frames_u8.dtype != torch.uint8 \
                or frames_u8.ndim != 4 or frames_u8.shape[-1] != 3:
            got = (f"{frames_u8.dtype} {tuple(frames_u8.shape)}" if isinstance(frames_u8, torch.Tensor)
                   else type(frames_u8).__name__)
            raise EncoderError(f"{self.spec.name}: preprocess expects a uint8 tensor [B,H,W,3], got {got}")
        s = self.spec.image_size
        x = frames_u8.to(self.device, non_blocking=True).permute(0, 3, 1, 2).float().div_(255)
        if tuple(x.shape[-2:]) != (s, s):
            x = F.interpolate(x, size=(s, s), mode=self.spec.interpolation, antialias=True,
                              align_corners=False).clamp_(0, 1)
        return (x - self.mean) / self.std

    def forward_grid(self, x: torch.Tensor) -> torch.Tensor:
        """[B,3,S,S] normalised pixels -> [B,gh,gw,C] float32 patch grid (no grad)."""
        s = self.spec.image_size
        if x.ndim != 4 or tuple(x.shape[1:]) != (3, s, s):
            raise EncoderError(f"{self.spec.name}: forward_grid expects [B,3,{s},{s}], got {tuple(x.shape)}")
        with torch.inference_mode(), self._autocast():
            grid = self._grid(x)
        want = (*self.spec.grid, self.spec.width)
        if tuple(grid.shape[1:]) != want:
            raise EncoderError(f"{self.spec.name}: model produced a grid {tuple(grid.shape[1:])}, spec says {want} "
                               f"(are the weights for {self.spec.model_id}?)")
        return grid.float()

    def forward_with_extras(self, x: torch.Tensor) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """(patch grid, extra token arrays by name): everything a cache stores of a frame. Only native
        towers have extras (their post-connector tokens)."""
        return self.forward_grid(x), {}

    def forward(self, frames_u8: torch.Tensor) -> torch.Tensor:
        return self.forward_grid(self.preprocess(frames_u8))

    def describe(self) -> dict[str, Any]:
        """Everything about the encoder that changes the numbers (it is part of the cache key);
        the weights are identified separately by `weights_info["sha256"]`."""
        s = self.spec
        return {"name": s.name, "library": s.library, "model_id": s.model_id, "image_size": s.image_size,
                "preprocessing": s.preprocessing(), "grid": list(s.grid), "width": s.width,
                "prefix_tokens": s.prefix_tokens, "tokens": s.tokens}

    def _grid(self, x: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError

    def _autocast(self) -> contextlib.AbstractContextManager:
        return contextlib.nullcontext() if self.compute_dtype is None else autocast(self.device, self.compute_dtype)


def tokens_to_grid(tokens: torch.Tensor, prefix: int, grid: tuple[int, int]) -> torch.Tensor:
    """ViT tokens [B,prefix+gh*gw,C] -> [B,gh,gw,C] (row-major patch order, prefix tokens dropped)."""
    if tokens.shape[1] != prefix + grid[0] * grid[1]:
        raise EncoderError(f"model returned {tokens.shape[1]} tokens; expected {prefix} prefix + "
                           f"{grid[0]}x{grid[1]} patch tokens")
    return tokens[:, prefix:].reshape(tokens.shape[0], grid[0], grid[1], tokens.shape[-1])


def feature_map_to_grid(fmap: torch.Tensor) -> torch.Tensor:
    """CNN feature map [B,C,h,w] -> [B,h,w,C]."""
    return fmap.permute(0, 2, 3, 1)
