"""What one extraction computes and where it writes: the `Job` (a request resolved against its dataset and
loaded encoder: cameras, episodes, the frames to cache; made by graftcache.extract.resolve.resolve_job) and the
`Target` (the cache key and its manifest in a root)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import polars as pl
import torch

from graftcache.datasets import LeRobotSource
from graftcache.requests import ExtractRequest
from graftcache.runtime import resolve_dtype
from graftcache.store import Manifest, Root


@dataclass(frozen=True)
class Job:
    """One request resolved: `req` with its compute dtype and grids resolved (never "auto" or "unpooled"), the
    opened dataset and loaded encoder, and the frames to cache."""

    req: ExtractRequest
    source: LeRobotSource
    encoder: Any
    cameras: list[str]
    episodes: list[int]
    index: pl.DataFrame    # the cached frames (every `frame_stride`-th), in cache order, with low-dim columns
    stream: pl.DataFrame   # every frame of the cached episodes: the full-rate action stream
    device: torch.device

    @property
    def compute(self) -> torch.dtype:
        return resolve_dtype(self.req.compute_dtype)


@dataclass(frozen=True)
class Target:
    """The cache a job fills: its key in a root, and the manifest that key hashes."""

    root: Root
    key: str
    manifest: Manifest
