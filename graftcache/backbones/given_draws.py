"""The draws inside a lerobot policy's forward and prediction (its flow time and noise), answered with the caller's:
what lets an adapter's `loss(batch, noise, time)` and `predict(batch, noise)` run lerobot's own code under fixed
draws (EO-1, GR00T, VLA-JEPA, Wall-X).

- `shadowed(module, **methods)`: instance attributes over an nn.Module's methods for the block (a sampler such as
  `sample_time` / `sample_noise`, or `predict` with other arguments bound).
- `given_noise(lerobot_module, noise, backbone)`: for the block, the global `torch` of one of lerobot's Python
  modules answers `randn` / `randn_like` with `noise` (refused in one line when the shape drawn is another) and is
  torch otherwise. Only that module's draws change, and no other call pays for it: a TorchFunctionMode would see
  every torch call of the forward, on the hot path of every fit step.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from types import ModuleType
from typing import Any

import torch
from torch import nn

from graftcache.backbones.patching import patched
from graftcache.errors import BackboneError

DRAWS = ("randn", "randn_like")


@contextlib.contextmanager
def shadowed(module: nn.Module, **methods) -> Iterator[None]:
    """Instance attributes shadowing `module`'s methods for the duration of the block
    (graftcache.backbones.patching.patched)."""
    with patched(module, **methods):
        yield


class DrawingTorch:
    """A lerobot module's `torch` while a draw is given: the draws named in `draws` return `noise`, on the device
    and in the dtype the call asks for (else the noise's own dtype, or `like`'s for randn_like); everything else,
    those draws included when not named, is torch's."""

    def __init__(self, noise: torch.Tensor, where: str, backbone: str, draws: tuple[str, ...]) -> None:
        self._noise, self._where, self._backbone, self._draws = noise, where, backbone, draws

    def _given(self, draw: str, shape: tuple[int, ...], device, dtype) -> torch.Tensor:
        if tuple(shape) != tuple(self._noise.shape):
            raise BackboneError(f"{self._backbone}: noise of shape {tuple(self._noise.shape)} given, {tuple(shape)} "
                                f"drawn by torch.{draw} in {self._where}")
        return self._noise.to(device=device, dtype=dtype)

    def randn(self, *size: Any, dtype=None, device=None, **kwargs: Any) -> torch.Tensor:
        if "randn" not in self._draws:
            return torch.randn(*size, dtype=dtype, device=device, **kwargs)
        if "size" in kwargs:
            size = kwargs["size"]
        elif len(size) == 1 and not isinstance(size[0], int):  # randn((B, T, D)) / randn(tensor.shape)
            size = size[0]
        return self._given("randn", tuple(size), device, dtype)

    def randn_like(self, like: torch.Tensor, *, dtype=None, device=None, **kwargs: Any) -> torch.Tensor:
        if "randn_like" not in self._draws:
            return torch.randn_like(like, dtype=dtype, device=device, **kwargs)
        return self._given("randn_like", like.shape, device or like.device, dtype or like.dtype)

    def __getattr__(self, name: str) -> Any:
        return getattr(torch, name)


@contextlib.contextmanager
def given_noise(module: ModuleType, noise: torch.Tensor, backbone: str,
                draws: tuple[str, ...] = DRAWS) -> Iterator[None]:
    """`module`'s draws named in `draws` return `noise` while the block runs (see DrawingTorch)."""
    with patched(module, torch=DrawingTorch(noise, module.__name__, backbone, draws)):
        yield
