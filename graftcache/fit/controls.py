"""Controls: what each results row's `control` means, declared as data (a registry, no if-chains).

- none            the plain graft: candidate encoder -> pool -> LN -> Linear, projector trained
- native          the released tower, no graft: cached post-connector tokens fed as-is (eval only)
- native-graft    the native tower's own patch grid through the wrapper (measures wrapper non-neutrality)
- zero-image      all-zero features: what the backbone does with no visual information
- shuffled-image  features of other frames (a fixed permutation within each split)
- pool-HxW        the candidate encoder pooled to another grid
- lora            LoRA adapters on the LM trained together with the projector

Each control owns its projector (how cached features become LM tokens) and its feature transform
(what it does to one split's features), so the fit only calls them.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import torch
from torch import nn

from graftcache.errors import FitError
from graftcache.graft import GraftProjector, IdentityProjector
from graftcache.pooling import format_grid, parse_grids

SHUFFLE_SEED_OFFSET = 7919

Features = dict[str, torch.Tensor]  # camera -> [N, T, C]
Projector = Callable[[int, int], nn.Module]  # (feature width, LM width) -> the module grafted in
Transform = Callable[[Features, int], Features]  # (one split's features, seed) -> what the policy sees


def keep(features: Features, seed: int) -> Features:
    return features


def zero(features: Features, seed: int) -> Features:
    return {c: torch.zeros_like(f) for c, f in features.items()}


def shuffle(features: Features, seed: int) -> Features:
    """Features of other frames: a fixed permutation (from `seed`) in which no frame keeps its own."""
    n = next(iter(features.values())).shape[0]
    g = torch.Generator().manual_seed(seed + SHUFFLE_SEED_OFFSET)
    perm = torch.randperm(n, generator=g)
    fixed = perm == torch.arange(n)
    if n > 1 and fixed.any():
        perm[fixed] = perm[fixed].roll(1) if fixed.sum() > 1 else perm[(torch.nonzero(fixed)[0] + 1) % n]
    return {c: f[perm] for c, f in features.items()}


def identity(width: int, lm_width: int) -> nn.Module:
    """The native control's projector: the cached connector tokens must already be the LM's width."""
    if width != lm_width:
        raise FitError(f"native connector tokens are {width} wide, the backbone's LM expects {lm_width}")
    return IdentityProjector(lm_width)


@dataclass(frozen=True)
class Control:
    name: str
    projector: Projector = GraftProjector
    transform: Transform = keep
    native_cache: bool = False      # reads the native tower's cache instead of the candidate encoder's
    extra: str | None = None        # reads this stored extra array instead of a pooled grid
    train: bool = True              # False: evaluated as loaded (its cell's objective is "eval")
    lora: bool = False              # LoRA adapters on the LM train with the projector
    grid: tuple[int, int] | None = None  # overrides the backbone's native grid


CONTROLS: dict[str, Control] = {
    "none": Control("none"),
    "native": Control("native", projector=identity, native_cache=True, extra="connector", train=False),
    "native-graft": Control("native-graft", native_cache=True),
    "zero-image": Control("zero-image", transform=zero),
    "shuffled-image": Control("shuffled-image", transform=shuffle),
    "lora": Control("lora", lora=True),
}
POOL_PREFIX = "pool-"


def get_control(name: str) -> Control:
    """Registry lookup; `pool-HxW` is parametric."""
    if name in CONTROLS:
        return CONTROLS[name]
    if name.startswith(POOL_PREFIX):
        try:
            (grid,) = parse_grids(name.removeprefix(POOL_PREFIX))
        except Exception:
            raise FitError(f"control {name!r}: expected pool-HxW, e.g. pool-4x4") from None
        return replace(CONTROLS["none"], name=f"{POOL_PREFIX}{format_grid(grid)}", grid=grid)
    raise FitError(f"unknown control {name!r}; choose from {', '.join(CONTROLS)}, {POOL_PREFIX}HxW")
