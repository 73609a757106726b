"""Controls: what each results row's `control` means, declared as data (a registry, no if-chains).

- none            the plain graft: candidate encoder -> pool -> LN -> Linear, projector trained
- native          the released tower, no graft: cached post-connector tokens fed as-is (eval only)
- native-graft    the native tower's own patch grid through the wrapper (measures wrapper non-neutrality)
- zero-image      all-zero features: what the backbone does with no visual information
- shuffled-image  features of other frames (a fixed pairing of frames within each split, see `shuffle`)
- pool-HxW        the candidate encoder pooled to another grid
- lora            LoRA adapters on the LM trained together with the projector
- noise-A         the candidate's features degraded by dose A in (0, 1), a step between the encoder and the blind
                  policy (graftcache/fit/dose.py)

Each control owns its projector (how cached features become LM tokens), its feature transform (what it does
to a batch's features) and its pairing (which frame's features go with which frame's state, action and target:
a split's features are streamed, never held, so a shuffle is a pairing applied to the low-dim rows, not a
permutation of a feature tensor), so the fit only calls them.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np
import torch
from torch import nn

from graftcache.errors import FitError
from graftcache.fit.dose import dose_name, parse_dose
from graftcache.graft import GraftProjector, PassThroughProjector
from graftcache.pooling import format_grid, parse_grids
from graftcache.requests import DOSE_PREFIX, NATIVE_CONTROL, NATIVE_GRAFT_CONTROL, POOL_PREFIX

SHUFFLE_SEED_OFFSET = 7919
SHUFFLE_GROUP = 64  # frames that exchange features as a group (see shuffle)

Features = dict[str, torch.Tensor]  # camera -> [N, T, C]
Projector = Callable[[int, int], nn.Module]  # (feature width, LM width) -> the module grafted in
Transform = Callable[[Features], Features]  # a batch's features -> what the policy sees
Pairing = Callable[[int, int], "np.ndarray | None"]  # (frames of a split, seed) -> frame r sees features of [r]


def keep(features: Features) -> Features:
    return features


def zero(features: Features) -> Features:
    return {c: torch.zeros_like(f) for c, f in features.items()}


def own(n: int, seed: int) -> None:
    """Every frame sees its own features (no pairing)."""


def derangement(n: int, generator: torch.Generator) -> torch.Tensor:
    """A permutation of n (> 1) in which nothing stays in place: a seeded random one, its fixed points then
    moved (several: rotated among themselves; one: swapped with its neighbour)."""
    perm = torch.randperm(n, generator=generator)
    fixed = torch.nonzero(perm == torch.arange(n)).flatten()
    if n > 1 and len(fixed) > 1:
        perm[fixed] = perm[fixed].roll(1)
    elif n > 1 and len(fixed) == 1:
        i, j = int(fixed[0]), (int(fixed[0]) + 1) % n
        perm[i], perm[j] = perm[j].clone(), perm[i].clone()
    return perm


def shuffle(n: int, seed: int) -> np.ndarray:
    """Features of other frames: frame r of a split (cache order) sees the features of frame pairing[r], a fixed
    permutation (from `seed`) in which no frame keeps its own.

    Frames exchange features by groups of SHUFFLE_GROUP consecutive frames (the last group takes the remainder):
    each group sees a seeded arrangement of another group's frames (a derangement of the groups, when there
    are at least two equal ones), else a derangement of its own. A group of a split is a run of one or two
    episodes, so a frame's features come from another episode, at a random time of it; and the frames one
    block of features goes with lie in a few runs, so `align` reads both sides run by run instead of frame by
    frame across the whole split.
    """
    g = torch.Generator().manual_seed(seed + SHUFFLE_SEED_OFFSET)
    equal = max(1, n // SHUFFLE_GROUP) - 1   # groups of exactly SHUFFLE_GROUP; the last one takes the rest
    others = derangement(equal, g) if equal >= 2 else torch.arange(equal)
    out = np.empty(n, dtype=np.int64)
    for group, partner in enumerate(others.tolist()):
        within = torch.randperm(SHUFFLE_GROUP, generator=g) if partner != group else derangement(SHUFFLE_GROUP, g)
        out[group * SHUFFLE_GROUP:(group + 1) * SHUFFLE_GROUP] = partner * SHUFFLE_GROUP + within.numpy()
    start = equal * SHUFFLE_GROUP
    out[start:] = start + derangement(n - start, g).numpy()
    return out


def pass_through(width: int, lm_width: int) -> nn.Module:
    """The native control's projector: the cached connector tokens must already be the LM's width."""
    if width != lm_width:
        raise FitError(f"native connector tokens are {width} wide, the backbone's LM expects {lm_width}")
    return PassThroughProjector(lm_width)


def zero_image_projector(width: int, lm_width: int) -> nn.Module:
    """The zero-image control's projector, whose function cannot depend on the encoder's width: the Linear weight and
    the LayerNorm bias start at zero, so with all-zero features their gradients stay exactly zero (LN(0) is its bias,
    the Linear's weight gradient is g x LN(0)^T, the LN bias's W^T g) and only the Linear bias, of LM width, trains,
    from zero. Built without drawing from torch's global generator (a default init draws width x lm_width numbers),
    so whatever the pass draws next does not depend on the width either."""
    with torch.random.fork_rng(devices=[]):
        projector = GraftProjector(width, lm_width)
    with torch.no_grad():
        projector.proj.weight.zero_()
        projector.proj.bias.zero_()
        projector.norm.bias.zero_()
    return projector


@dataclass(frozen=True)
class Control:
    name: str
    projector: Projector = GraftProjector
    transform: Transform = keep     # applied to every batch's features
    pairing: Pairing = own          # which frame's features each frame sees
    native_cache: bool = False      # reads the native tower's cache instead of the candidate encoder's
    extra: str | None = None        # reads this stored extra array instead of a pooled grid
    train: bool = True              # False: evaluated as loaded (its cell's objective is "eval")
    lora: bool = False              # LoRA adapters on the LM train with the projector
    fuses: bool = True              # may share a backbone pass with other cells (graftcache/fit/passes.py); LoRA
                                    # adapts the backbone itself, which every row of a pass would go through
    grid: tuple[int, int] | None = None  # overrides the backbone's token grid
    closed_loop: bool = True        # has a meaning as a policy run in the simulator (graftcache export, rollout)
    ignores: tuple[str, ...] = ()   # cell fields its policy's function does not depend on (its policy_id leaves them
                                    # out, graftcache.fit.plan.Plan.policy_id, or hashes what stands in for them)
    dose: float | None = None       # noise-A: features degraded by dose A, seeded per frame (graftcache/fit/dose.py)


CONTROLS: dict[str, Control] = {
    "none": Control("none"),
    # the tower as released, trained by nothing: the seed changes nothing (scoring's noise is fixed per frame), and
    # a cell that trains nothing holds no training setting (graftcache.settings.Identity's `when`)
    NATIVE_CONTROL: Control(NATIVE_CONTROL, projector=pass_through, native_cache=True, extra="connector", train=False,
                            ignores=("seed",)),
    NATIVE_GRAFT_CONTROL: Control(NATIVE_GRAFT_CONTROL, native_cache=True),
    # zeroed features: the encoder's cache decides nothing but which frames train (what stands in for its key)
    "zero-image": Control("zero-image", projector=zero_image_projector, transform=zero, ignores=("cache_key",)),
    "shuffled-image": Control("shuffled-image", pairing=shuffle, closed_loop=False),  # other frames: none live
    "lora": Control("lora", lora=True, fuses=False),
}


def check_pool_grid(control: Control, stored: Sequence[tuple[int, int]], cache: str) -> str | None:
    """A pool-HxW control finer than the finest grid `cache` stores (`stored`) is up-sampled by read_grid, which
    adds no information. Twice as fine or more (pool-16x16 on an 8x8 cache) each stored cell is only repeated: refused.
    Finer by less, neighbouring cells are blended, as for any encoder meeting a backbone grid finer than its own
    (clip-b16's 14x14 and pi0.5's 16x16; the paper's pool-16x16 control of clip-b16): returned as a note to log."""
    if control.grid is None or control.grid in stored:
        return None
    finest = max(stored, key=lambda g: g[0] * g[1])
    (h, w), (fh, fw) = control.grid, finest
    if h >= 2 * fh or w >= 2 * fw:
        raise FitError(f"control {control.name}: {cache} stores grids no finer than {format_grid(finest)}, so "
                       f"{format_grid(control.grid)} would only repeat its cells; choose {POOL_PREFIX}HxW with "
                       f"H < {2 * fh} and W < {2 * fw}, or extract a finer grid")
    if h > fh or w > fw:
        return (f"control {control.name}: {cache} stores grids no finer than {format_grid(finest)}: its cells are "
                f"blended up to {format_grid(control.grid)}")
    return None


def get_control(name: str) -> Control:
    """Registry lookup; `pool-HxW` and `noise-A` are parametric."""
    if name in CONTROLS:
        return CONTROLS[name]
    if name.startswith(POOL_PREFIX):
        try:
            (grid,) = parse_grids(name.removeprefix(POOL_PREFIX))
        except Exception:
            raise FitError(f"control {name!r}: expected pool-HxW, e.g. pool-4x4") from None
        return replace(CONTROLS["none"], name=f"{POOL_PREFIX}{format_grid(grid)}", grid=grid)
    if name.startswith(DOSE_PREFIX):
        level = parse_dose(name)
        return replace(CONTROLS["none"], name=dose_name(level), dose=level)
    raise FitError(f"unknown control {name!r}; choose from {', '.join(CONTROLS)}, {POOL_PREFIX}HxW, {DOSE_PREFIX}A")
