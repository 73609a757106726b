"""The graft wrapper shared by every backbone: the batch key of cached features and the projectors.

The method under test feeds a candidate encoder's cached patch tokens (already pooled to the
backbone's token grid upstream) into a frozen VLA through one fixed wrapper:

    features [B, T, enc_dim] -> LayerNorm(enc_dim) -> Linear(enc_dim -> LM width)

The wrapper is deliberately the same for every encoder, so that differences in the fitted loss
are differences between encoders, not between adapters. How it is put into a policy (pass-through
tower, freezing, undo) is graftcache.backbones.surgery.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager

import torch
import torch.nn.functional as F
from torch import nn

FEATURE_PREFIX = "observation.vis_feats."


def feature_key(camera: str) -> str:
    """Batch key of a camera's cached features, e.g. "image" -> "observation.vis_feats.image".

    Not `observation.images.*`: lerobot's AddBatchDimensionProcessorStep unsqueezes every 3-D tensor
    under that prefix (it takes [B, T, D] features for one [C, H, W] image).
    """
    return FEATURE_PREFIX + camera.removeprefix("observation.images.")


class GraftProjector(nn.Module):
    """LayerNorm(enc_dim) -> Linear(enc_dim, lm_width): the only trainable module of a graft.

    Kept in float32 whatever the backbone's dtype: the cache may hold fp16/bf16 features and the
    optimiser state of a few hundred thousand parameters is cheap. The backbones cast its output to
    their own layer dtype.

    The norm's scale and shift are applied after torch's layer_norm, not inside it: its fused backward sums their
    gradients over rows in one partial sum per intra-op thread, so a fit's numbers depended on the thread count;
    the gradients of a product and a sum are reduced over rows with each output column summed whole by one thread.
    """

    def __init__(self, enc_dim: int, lm_width: int) -> None:
        super().__init__()
        self.norm = nn.LayerNorm(enc_dim)
        self.proj = nn.Linear(enc_dim, lm_width)
        self.in_features, self.out_features = enc_dim, lm_width

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        norm = self.norm
        normed = F.layer_norm(features.to(self.proj.weight.dtype), norm.normalized_shape, eps=norm.eps)
        return self.proj(normed * norm.weight + norm.bias)


class PassThroughProjector(nn.Module):
    """The `native` control: cached post-connector tokens are fed as they are (no parameters).

    The backbone still applies its own post-connector scaling (SmolVLA multiplies by sqrt(width)),
    exactly as it does for its native tokens.
    """

    def __init__(self, width: int) -> None:
        super().__init__()
        self.in_features = self.out_features = width

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        return features.float()


class FusedProjector(nn.Module):
    """The projectors of several cells grafted at once (graftcache/fit/passes.py): member i projects the i-th
    run of rows of every batch, so the cells share one forward and backward of the frozen backbone while each
    projector sees only its own cell's frames. The frozen backbone treats the samples of a batch independently,
    so each member's gradient is its own cell's.

    How many rows each member owns is set around each forward (`rows`); the members must agree on widths."""

    def __init__(self, members: Sequence[nn.Module]) -> None:
        super().__init__()
        widths = {(m.in_features, m.out_features) for m in members}
        if len(widths) != 1:
            raise ValueError(f"fused projectors must share their widths, got {sorted(widths)}")
        self.members = nn.ModuleList(members)
        (self.in_features, self.out_features), = widths
        self._rows: list[int] | None = None

    @contextmanager
    def rows(self, sizes: Sequence[int]) -> Iterator[None]:
        """Member i projects `sizes[i]` rows (in member order) of the batches forwarded inside the block."""
        self._rows = list(sizes)
        try:
            yield
        finally:
            self._rows = None

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        if self._rows is None or sum(self._rows) != features.shape[0]:
            raise RuntimeError(f"a fused projector needs its members' rows of a batch of {features.shape[0]}, "
                               f"has {self._rows}")
        parts = features.split(self._rows)
        return torch.cat([m(part) for m, part in zip(self.members, parts, strict=True)])


def at_width(saved: dict[str, torch.Tensor], build: Callable[[int, int], nn.Module],
             width: int) -> dict[str, torch.Tensor]:
    """A fit's saved trainable parameters (full adapter names, one GraftProjector among them) for a projector that
    takes features `width` wide, as `build` (width, LM width) makes it; `saved` itself where the widths are equal.
    For the copy of a policy whose function does not depend on the width (the zero-image control's:
    graftcache.fit.controls.zero_image_projector) made for a cell of another cache's width, which an export grafts at
    that cell's width. Exact only because every parameter whose shape depends on the width never trained: each must
    still equal its init, else ValueError names it (the copy would be another policy). Parameters of the width's
    shape (or outside the projector) are kept as saved."""
    weights = [n for n in saved if (n == "proj.weight" or n.endswith(".proj.weight"))
               and n.removesuffix("proj.weight") + "norm.weight" in saved]
    if len(weights) != 1:
        raise ValueError(f"no single graft projector among the saved parameters ({len(weights)} found)")
    prefix = weights[0].removesuffix("proj.weight")
    lm_width, was = saved[weights[0]].shape
    if was == width:
        return saved
    old, new = build(was, lm_width).state_dict(), build(width, lm_width).state_dict()
    out = dict(saved)
    for key, init in old.items():
        value = saved[prefix + key]
        if value.shape == new[key].shape:
            continue
        if not torch.equal(value, init.to(value.dtype)):
            raise ValueError(f"{prefix + key} trained away from its init, so the projector's function depends on "
                             f"its width ({was})")
        out[prefix + key] = new[key].to(value.dtype).contiguous()
    return out
