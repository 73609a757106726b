"""Camera frames -> the features a cell was scored on, computed the way the cache computed and read them.

Extraction (graftcache.extract.encode) runs the encoder on uint8 frames under the cache's compute dtype, pools
each stored grid in fp32 and rounds it to the storage dtype; a fit reads the grid at its pool grid
(graftcache.fit.data.read_grid): stored as such, or pooled in fp32 from the stored unpooled grid and rounded again.
`CellFeatures` does the same steps on the simulator's (or a dataset's) frames, so a closed-loop step sees what the
offline score saw, up to the decoding of the pixels. A dose cell's features are then degraded as its fit and scoring
degraded them (graftcache.fit.dose.dosed, with the spread its run folder saved), each predicted chunk's frame keyed by
the count of chunks since the policy's reset at the episode's start.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import torch

from graftcache.encoders import Encoder
from graftcache.encoders.fingerprint import compare, encoder_of, fingerprint
from graftcache.errors import ExportError
from graftcache.fit.controls import get_control
from graftcache.fit.controls import zero as zero_features
from graftcache.fit.dose import SPREAD_FILE, Dose, read_spread
from graftcache.graft import feature_key
from graftcache.pooling import format_grid, parse_grid, pool_grid
from graftcache.runtime import autocast, resolve_dtype
from graftcache.store import Manifest

MANIFEST_FILE = "manifest.json"
IMAGE_PREFIX = "observation.images."


def to_uint8(images: torch.Tensor) -> torch.Tensor:
    """lerobot's [B, 3, H, W] float pixels in [0, 1] -> the uint8 [B, H, W, 3] frames encoders take (the
    simulator's and a dataset's frames are uint8 to begin with, so this is exact)."""
    return images.mul(255).round().clamp(0, 255).to(torch.uint8).permute(0, 2, 3, 1)


class CellFeatures:
    """One cell's feature path: encoder, stored grid (or the native `connector` tokens), storage rounding, pooling."""

    def __init__(self, encoder: Encoder, manifest: Manifest, pool: str, *, extra: str | None, zero: bool,
                 dose: Dose | None = None) -> None:
        self.encoder, self.extra, self.zero, self.dose = encoder, extra, zero, dose
        self.chunks = 0  # chunks predicted since the last reset: the key of the next frame's dose noise
        self.compute = resolve_dtype(manifest.compute_dtype)
        self.storage = resolve_dtype(manifest.storage_dtype)
        self.pool = parse_grid(pool)
        stored = manifest.grids
        self.stored = parse_grid(pool if pool in stored else (manifest.unpooled_grid or max(
            stored, key=lambda g: math.prod(parse_grid(g)))))

    @torch.no_grad()
    def __call__(self, images: torch.Tensor) -> torch.Tensor:
        """[B, 3, H, W] in [0, 1] -> [B, T, C] features (float32 holding storage-dtype values)."""
        x = self.encoder.preprocess(to_uint8(images))
        with torch.inference_mode(), autocast(self.encoder.device, self.compute):
            grid, extras = self.encoder.forward_with_extras(x)
        if self.extra is not None:
            out = extras[self.extra].float().to(self.storage).float()
        else:
            out = pool_grid(grid.float(), self.stored).to(self.storage)
            if self.stored != self.pool:
                h, w = self.stored
                out = pool_grid(out.float().reshape(len(out), h, w, -1), self.pool).to(self.storage)
            out = out.float()
        return torch.zeros_like(out) if self.zero else out

    def observe(self, batch: dict, cameras: dict[str, str], where: str) -> dict:
        """`batch` with its camera frames replaced by the cell's features, for every policy camera from the camera
        the cell mapped to it (`cameras`), as graftcache.fit.loop.raw_batch holds them; the frames leave the batch,
        as offline scoring never had them. A missing camera is an ExportError naming `where` (the export)."""
        check_cameras(batch, cameras, where)
        observation = dict(batch)
        frames = {k: observation.pop(k) for k in list(observation) if k.startswith(IMAGE_PREFIX)}
        seen = {}
        for camera in dict.fromkeys(cameras.values()):
            images = frames[IMAGE_PREFIX + camera].to(self.encoder.device)
            seen[camera] = self(images if images.ndim == 4 else images[None])
        if self.dose is not None:  # frame i of the batch: key chunks * B + i (one frame per episode: the count)
            n = len(next(iter(seen.values())))
            seen = self.dose(seen, self.chunks * n + np.arange(n))
        self.chunks += 1
        for policy_camera, camera in cameras.items():
            observation[feature_key(policy_camera)] = seen[camera]
        return observation

    def reset(self) -> None:
        """An episode starts: its dose noise starts again from its first key."""
        self.chunks = 0

    def describe(self) -> str:
        what = self.extra or f"grid {format_grid(self.stored)} pooled to {format_grid(self.pool)}"
        dosed = f" (dose {self.dose.level:g}, seed {self.dose.seed})" if self.dose is not None else ""
        return f"{self.encoder.spec.name}: {what}" + (" (zeroed: zero-image)" if self.zero else "") + dosed


def check_cameras(observation: dict, cameras: dict[str, str], where: str) -> None:
    """Refuse, in one line naming `where` (the export), an observation without a frame of a camera the cell reads."""
    for policy_camera, camera in cameras.items():
        if IMAGE_PREFIX + camera not in observation:
            raise ExportError(f"{where}: the observation has no {IMAGE_PREFIX}{camera} (it feeds policy camera "
                              f"{policy_camera}); pass lerobot-eval a --rename_map that provides it")


def read_manifest(folder: Path) -> Manifest:
    """The cache manifest an export carries (how to rebuild its encoder, its numerics fingerprint)."""
    path = folder / MANIFEST_FILE
    try:
        raw = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise ExportError(f"{path}: cannot read the cache manifest of this export ({e})") from None
    return Manifest.read(raw["manifest"], str(path), raw["key"])


def load_cell_features(folder: Path, config: dict, device: str) -> CellFeatures:
    """An export's feature path, its encoder rebuilt from the manifest and its numerics fingerprint recomputed here:
    an environment whose encoder computes other features than the ones the cell was scored on is refused in one
    line, as `fit` refuses it (`accept_numerics_drift` in config.json lets it run)."""
    manifest = read_manifest(folder)
    encoder = encoder_of(manifest, device)
    if encoder.weights_info.get("sha256") != manifest.weights_sha256:
        raise ExportError(f"{folder}: the {manifest.encoder_name} weights found here are not those of cache "
                          f"{config['cache_key']}")
    recorded = manifest.numerics
    check = compare(config["cache_key"], recorded, fingerprint(encoder, recorded["compute_dtype"], device),
                    manifest.versions)
    if check.status == "drift" and not config.get("accept_numerics_drift"):
        raise ExportError(f"{folder}: {check.line()}; refused (set accept_numerics_drift in its config.json to run it)")
    control = get_control(config["control"])
    dose = None
    if control.dose is not None:
        dose = Dose(control.dose, read_spread(folder / SPREAD_FILE), int(config["dose_seed"]))
    return CellFeatures(encoder, manifest, config["pool_grid"], extra=control.extra,
                        zero=control.transform is zero_features, dose=dose)
