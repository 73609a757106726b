"""Helpers for the encoder tests: a fake Hugging Face hub cache, real photos, frames."""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

REV = "0123456789abcdef0123456789abcdef01234567"


def hub_cache_dir() -> Path:
    """The hub cache the conftest points every test at (read at call time, like graftcache does)."""
    return Path(os.environ["HF_HUB_CACHE"])


def fake_hub_snapshot(repo_id: str, files: dict[str, Callable[[Path], object]]) -> Path:
    """The huggingface_hub cache layout, models--org--name/{refs/main, snapshots/<rev>/...}; each
    `files[name](path)` writes one file (real hub caches hold symlinks into blobs/, read the same)."""
    base = hub_cache_dir() / ("models--" + repo_id.replace("/", "--"))
    snap = base / "snapshots" / REV
    snap.mkdir(parents=True, exist_ok=True)
    (base / "refs").mkdir(exist_ok=True)
    (base / "refs" / "main").write_text(REV)
    for name, write in files.items():
        write(snap / name)
    return snap


def photo(name: str, size: int = 256) -> np.ndarray:
    """A scikit-image sample photo, centre-cropped square (framed like a robot camera) and resized, uint8."""
    import skimage.data
    from PIL import Image

    img = getattr(skimage.data, name)()
    h, w = img.shape[:2]
    s = min(h, w)
    img = img[(h - s) // 2:(h - s) // 2 + s, (w - s) // 2:(w - s) // 2 + s]
    return np.asarray(Image.fromarray(img).resize((size, size), Image.BICUBIC))


def random_frames(n: int, h: int = 256, w: int = 256, seed: int = 0) -> torch.Tensor:
    """Smooth-ish uint8 frames [n,h,w,3] (noise on a gradient, so resizing has something to do)."""
    g = torch.Generator().manual_seed(seed)
    ramp = torch.linspace(0, 200, w).view(1, 1, w, 1).expand(n, h, w, 3)
    noise = torch.randint(0, 56, (n, h, w, 3), generator=g).float()
    return (ramp + noise).clamp(0, 255).to(torch.uint8)
