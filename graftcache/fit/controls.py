"""Controls: what each results row's `control` means, declared as data (a registry, no if-chains).

- none            the plain graft: candidate encoder -> pool -> LN -> Linear, projector trained
- native          the released tower, no graft: cached post-connector tokens fed as-is (eval only)
- native-graft    the native tower's own patch grid through the wrapper (measures wrapper non-neutrality)
- zero-image      all-zero features: what the backbone does with no visual information
- shuffled-image  features of other frames (a fixed permutation within each split)
- pool-HxW        the candidate encoder pooled to another grid
- lora            LoRA adapters on the LM trained together with the projector
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import torch

from graftcache.errors import FitError
from graftcache.pooling import format_grid, parse_grids

SHUFFLE_SEED_OFFSET = 7919


@dataclass(frozen=True)
class Control:
    name: str
    features: str = "encoder"       # "encoder" | "native-grid" | "native-tokens"
    projector: str = "graft"        # "graft" | "identity"
    train: bool = True
    lora: bool = False
    transform: str = "none"         # "none" | "zero" | "shuffle"
    grid: tuple[int, int] | None = None  # overrides the backbone's native grid

    @property
    def uses_native_cache(self) -> bool:
        return self.features != "encoder"


CONTROLS: dict[str, Control] = {
    "none": Control("none"),
    "native": Control("native", features="native-tokens", projector="identity", train=False),
    "native-graft": Control("native-graft", features="native-grid"),
    "zero-image": Control("zero-image", transform="zero"),
    "shuffled-image": Control("shuffled-image", transform="shuffle"),
    "lora": Control("lora", lora=True),
}


def get_control(name: str) -> Control:
    """Registry lookup; `pool-HxW` is parametric."""
    if name in CONTROLS:
        return CONTROLS[name]
    if name.startswith("pool-"):
        try:
            (grid,) = parse_grids(name.removeprefix("pool-"))
        except Exception:
            raise FitError(f"control {name!r}: expected pool-HxW, e.g. pool-4x4") from None
        return replace(Control(f"pool-{format_grid(grid)}"), grid=grid)
    raise FitError(f"unknown control {name!r}; choose from {', '.join(CONTROLS)}, pool-HxW")


def transform_features(features: dict[str, torch.Tensor], control: Control, seed: int) -> dict[str, torch.Tensor]:
    """Apply the control's feature transform (zero or shuffle) to one split's features."""
    if control.transform == "none":
        return features
    if control.transform == "zero":
        return {c: torch.zeros_like(f) for c, f in features.items()}
    n = next(iter(features.values())).shape[0]
    g = torch.Generator().manual_seed(seed + SHUFFLE_SEED_OFFSET)
    perm = torch.randperm(n, generator=g)
    fixed = perm == torch.arange(n)  # a frame must not keep its own features
    if n > 1 and fixed.any():
        perm[fixed] = perm[fixed].roll(1) if fixed.sum() > 1 else perm[(torch.nonzero(fixed)[0] + 1) % n]
    return {c: f[perm] for c, f in features.items()}
