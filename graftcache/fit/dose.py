"""The dose family `noise-A`: a candidate encoder's features degraded in known steps, from the encoder (A = 0) to
the blind policy (A -> 1), to measure what offline MSE resolves against what the closed loop confirms.

One transform, variance-preserving noise at the features' own per-channel scale:

    f' = sqrt(1 - A) * f + sqrt(A) * spread * eps,    eps ~ N(0, 1) per frame, token and channel

Why this one. Its level is a measurable quantity: per channel the dosed features keep the clean ones' variance and
correlate with them by exactly sqrt(1 - A), so the doses are ordered by how much of the image they keep, and A -> 1
is noise that carries nothing about the frame (the zero-image control's blindness, at the features' scale). The
projector's LayerNorm sees inputs of one scale at every dose, so the dose measures lost information, not a scale
the projector must learn anew. It needs nothing but the frame it degrades: a blend with another frame's features
has no other frame inside a closed-loop policy, and token dropout changes how many tokens carry a signal, not how
much each carries, and zeroed tokens are a scale change.

`spread` (the per-channel standard deviation over frames and tokens) is one fixed statistic per (cache, grid,
camera), measured on evenly spaced frames of the training split (SPREAD_FRAMES), saved beside the projector in the
run folder (SPREAD_FILE) and carried into the export, so fit, offline scoring and the exported policy scale the noise
alike. The noise of a frame is drawn from a generator seeded by (the cell's seed, the frame's key): offline the key
is the frame's cache row (training and scoring, so scores reproduce and a frame always meets one draw), inside an
exported policy the count of chunks it predicted since lerobot's `reset` at the episode's start (so a rerun of an
episode is the same episode). One function, `dosed`, draws it everywhere.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch
from safetensors.torch import load_file, save_file

from graftcache.errors import FitError, GraftcacheError
from graftcache.requests import DOSE_PREFIX

if TYPE_CHECKING:
    from graftcache.fit.data import LowDim
    from graftcache.fit.stream import FeatureSource

Features = dict[str, torch.Tensor]  # camera -> [N, T, C]
#: A batch's features, and the keys of the frames that see them -> what the policy sees.
FrameTransform = Callable[[Features, np.ndarray], Features]

SPREAD_FILE = "spread.safetensors"   # in a dose cell's run folder and its export: spread per camera
SPREAD_FRAMES = 1024                 # training frames the spread is measured on (evenly spaced, deterministic)
SPREAD_READ = 128                    # frames read at once while measuring it
DOSE_ENTROPY = 0x646F7365            # mixed into every frame's noise seed: no other draw of a cell's seed repeats it


def parse_dose(name: str) -> float:
    """The level A of control `noise-A`, in (0, 1); anything else is refused in one line."""
    text = name.removeprefix(DOSE_PREFIX)
    try:
        level = float(text)
    except ValueError:
        level = math.nan
    if not 0.0 < level < 1.0:
        raise FitError(f"control {name!r}: expected {DOSE_PREFIX}A with A strictly between 0 and 1, "
                              f"e.g. {DOSE_PREFIX}0.5 (0 is the plain cell, 1 the blind zero-image control)")
    return level


def dose_name(level: float) -> str:
    """The control name of dose `level`, written one way (noise-0.50 and noise-0.5 are one cell) that reads back as
    `level` exactly."""
    return f"{DOSE_PREFIX}{level!r}"


def frame_seed(seed: int, key: int) -> int:
    """The seed of one frame's noise: (the cell's seed, the frame's key) mixed, distinct pairs far apart."""
    return int(np.random.SeedSequence((DOSE_ENTROPY, int(seed), int(key))).generate_state(1, np.uint64)[0])


def dosed(features: Features, keys: np.ndarray, level: float, spread: Mapping[str, torch.Tensor],
          seed: int) -> Features:
    """`features` (camera -> [N, T, C]) at dose `level`: frame i's noise drawn from frame_seed(seed, keys[i]),
    cameras in name order, [T, C] each; float32 out, whatever precision came in."""
    keep, add = math.sqrt(1.0 - level), math.sqrt(level)
    cameras = sorted(features)
    if len(keys) != len(features[cameras[0]]):  # every frame must be keyed, or its noise would be left unset
        raise FitError(f"{len(keys)} keys for {len(features[cameras[0]])} frames of dose features")
    noise = {c: torch.empty(features[c].shape, dtype=torch.float32) for c in cameras}
    for i, key in enumerate(np.asarray(keys).tolist()):
        g = torch.Generator().manual_seed(frame_seed(seed, key))
        for c in cameras:
            noise[c][i] = torch.randn(features[c].shape[1:], generator=g)
    return {c: keep * features[c].float() + add * spread[c].to(features[c].device).float()
            * noise[c].to(features[c].device) for c in cameras}


@dataclass(frozen=True)
class Dose:
    """A dose cell's degradation: its level, the spread it scales the noise by, the cell's seed."""

    level: float
    spread: dict[str, torch.Tensor] = field(repr=False)
    seed: int

    def __call__(self, features: Features, keys: np.ndarray) -> Features:
        return dosed(features, keys, self.level, self.spread, self.seed)

    def save(self, folder: Path) -> None:
        save_file({c: s.contiguous() for c, s in self.spread.items()}, str(folder / SPREAD_FILE))


def read_spread(path: Path) -> dict[str, torch.Tensor]:
    """A saved spread (camera -> [C]); a missing or unreadable file is refused in one line naming it."""
    try:
        return load_file(str(path))
    except (OSError, ValueError) as e:
        raise GraftcacheError(f"{path}: cannot read the dose cell's feature spread ({e})") from None


def measure_spread(source: FeatureSource, train: LowDim) -> dict[str, torch.Tensor]:
    """Per camera, each channel's standard deviation over SPREAD_FRAMES evenly spaced training frames and their
    tokens (float64 sums, float32 out)."""
    rows = np.sort(train.evenly(SPREAD_FRAMES).rows)
    out = {}
    for camera in source.cameras:
        total = square = None
        n = 0
        for start in range(0, len(rows), SPREAD_READ):
            x = source.read_camera(camera, rows[start:start + SPREAD_READ]).double().flatten(0, -2)
            total = x.sum(0) if total is None else total + x.sum(0)
            square = (x * x).sum(0) if square is None else square + (x * x).sum(0)
            n += len(x)
        mean = total / n
        out[camera] = (square / n - mean * mean).clamp(min=0).sqrt().float()
    return out


@dataclass(frozen=True)
class Seen:
    """What a cell's policy sees of a batch: its control's transform (graftcache.fit.controls.Control.transform), then
    its dose where it has one (`keys`: the frames' cache rows)."""

    transform: Callable[[Features], Features] | None = None
    dose: Dose | None = None

    def __call__(self, features: Features, keys: np.ndarray) -> Features:
        out = features if self.transform is None else self.transform(features)
        return out if self.dose is None else self.dose(out, keys)


AS_IS = Seen()  # features as they are streamed: no control's transform, no dose
