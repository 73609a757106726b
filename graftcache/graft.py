"""The graft wrapper shared by every backbone: projector, pass-through tower, freezing.

The method under test feeds a candidate encoder's cached patch tokens (already pooled to the
backbone's token grid upstream) into a frozen VLA through one fixed wrapper:

    features [B, T, enc_dim] -> LayerNorm(enc_dim) -> Linear(enc_dim -> LM width)

The wrapper is deliberately the same for every encoder, so that differences in the fitted loss
are differences between encoders, not between adapters. The backbone's vision tower is replaced by
`PassThroughTower` (so lerobot's own `embed_image` runs unchanged and simply receives features), and
its connector by the projector. Everything but the projector is frozen.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass

import torch
from torch import nn
from transformers.modeling_outputs import BaseModelOutput

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
    """

    def __init__(self, enc_dim: int, lm_width: int) -> None:
        super().__init__()
        self.norm = nn.LayerNorm(enc_dim)
        self.proj = nn.Linear(enc_dim, lm_width)
        self.in_features, self.out_features = enc_dim, lm_width

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        return self.proj(self.norm(features.to(self.proj.weight.dtype)))


class IdentityProjector(nn.Module):
    """The `native` control: cached post-connector tokens are fed as they are (no parameters).

    The backbone still applies its own post-connector scaling (SmolVLA multiplies by sqrt(width)),
    exactly as it does for its native tokens.
    """

    def __init__(self, width: int) -> None:
        super().__init__()
        self.in_features = self.out_features = width

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        return features.float()


class PassThroughTower(nn.Module):
    """Stands in for a Hugging Face vision tower: returns its input as `.last_hidden_state`.

    `.dtype` exists because SmolVLA's `embed_image` casts its input to `vision_model.dtype`.
    """

    def __init__(self) -> None:
        super().__init__()
        self.register_buffer("_dtype_anchor", torch.zeros(0), persistent=False)

    @property
    def dtype(self) -> torch.dtype:
        return self._dtype_anchor.dtype

    def forward(self, pixel_values: torch.Tensor, **_: object) -> BaseModelOutput:
        return BaseModelOutput(last_hidden_state=pixel_values)


def freeze_all_but(model: nn.Module, trainable: nn.Module) -> None:
    """Freeze every parameter of `model`, then unfreeze those of `trainable` (which may be outside it)."""
    for p in model.parameters():
        p.requires_grad_(False)
    for p in trainable.parameters():
        p.requires_grad_(True)


@dataclass(frozen=True)
class FreezeRow:
    module: str
    params: int
    trainable: int


@dataclass(frozen=True)
class FreezeReport:
    """Which modules are frozen or trainable, with parameter counts (logged by the fit loop)."""

    rows: tuple[FreezeRow, ...]

    @property
    def total(self) -> int:
        return sum(r.params for r in self.rows)

    @property
    def trainable(self) -> int:
        return sum(r.trainable for r in self.rows)

    def __str__(self) -> str:
        width = max(len(r.module) for r in self.rows)
        lines = [f"{'module':<{width}}  {'params':>13}  {'trainable':>13}  state"]
        for r in self.rows:
            state = "trainable" if r.trainable == r.params and r.params else "frozen" if not r.trainable else "partial"
            lines.append(f"{r.module:<{width}}  {r.params:>13,}  {r.trainable:>13,}  {state}")
        lines.append(f"{'total':<{width}}  {self.total:>13,}  {self.trainable:>13,}")
        return "\n".join(lines)


def freeze_report(groups: Mapping[str, nn.Module | tuple[nn.Module, ...]], model: nn.Module) -> FreezeReport:
    """Count parameters per named group; each parameter is counted once (tied weights included),
    and anything not covered by a group is reported as "other" so the totals match `model`."""
    seen: set[int] = set()
    rows = []

    def count(params: Iterable[nn.Parameter]) -> tuple[int, int]:
        total = trainable = 0
        for p in params:
            if id(p) in seen:
                continue
            seen.add(id(p))
            total += p.numel()
            trainable += p.numel() if p.requires_grad else 0
        return total, trainable

    for name, modules in groups.items():
        modules = modules if isinstance(modules, tuple) else (modules,)
        total, trainable = count(p for m in modules for p in m.parameters())
        rows.append(FreezeRow(name, total, trainable))
    total, trainable = count(model.parameters())
    if total:
        rows.append(FreezeRow("other", total, trainable))
    return FreezeReport(tuple(rows))
