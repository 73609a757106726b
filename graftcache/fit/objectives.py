"""Objectives: how a cell's grafted projector is fitted, declared as data (a registry, no if-chains).

- flow   the policy's own flow-matching loss, back-propagated into the projector (and LoRA), for `steps`
         AdamW steps of `batch_size` at `lr` (fit/loop.py)
- align  closed-form ridge regression of the native tower's post-connector tokens on the candidate's
         features (fit/align.py): no steps, no learning rate, needs the native tower's cache
- eval   (not selectable) controls that train nothing, such as `native`, are scored as loaded
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch

from graftcache.fit.align import fit_ridge
from graftcache.fit.data import FrameTable
from graftcache.fit.loop import train
from graftcache.requests import FitRequest

if TYPE_CHECKING:
    from graftcache.backbones.base import BackboneAdapter


@dataclass(frozen=True)
class Fitting:
    """What an objective fits from: the grafted adapter, the split's tables and transformed features."""

    adapter: BackboneAdapter
    req: FitRequest
    train: FrameTable
    features: Mapping[str, torch.Tensor]       # train features after the control's transform
    cams: Mapping[str, str]                    # policy camera key -> cache camera
    targets: FrameTable | None                 # native post-connector tokens of the train split (align)
    grid: tuple[int, int]
    seed: int
    dtype: torch.dtype


def _flow(f: Fitting) -> float:
    return train(f.adapter, f.train, f.cams, steps=f.req.steps, batch_size=f.req.batch_size, lr=f.req.lr, seed=f.seed,
                 dtype=f.dtype, features=f.features, show=f.req.progress)


def _align(f: Fitting) -> float:
    cameras = list(f.cams.values())
    r2 = fit_ridge(f.adapter.projector, [f.features[c] for c in cameras], [f.targets.features[c] for c in cameras],
                   f.grid)
    return 1.0 - r2


def _nothing(f: Fitting) -> float:
    return float("nan")


@dataclass(frozen=True)
class Objective:
    name: str
    fit: Callable[[Fitting], float]   # fits the grafted projector; returns the final training loss
    scheduled: bool = False           # steps / lr / batch_size are part of its cells (else recorded as 0)
    needs_native: bool = False        # reads the native tower's cache (its regression targets)


OBJECTIVES: dict[str, Objective] = {
    "flow": Objective("flow", _flow, scheduled=True),
    "align": Objective("align", _align, needs_native=True),
}
EVAL_ONLY = Objective("eval", _nothing)
