"""Backbone registry: "smolvla" | "pi05" -> adapter class (see base.BackboneAdapter).

Adapters are imported on first use: importing lerobot costs ~5 s, which commands such as
`graftcache ls` should not pay.
"""

from __future__ import annotations

import importlib
from pathlib import Path
from typing import TYPE_CHECKING

from graftcache.backbones.tiny import TinySpec
from graftcache.errors import BackboneError

if TYPE_CHECKING:
    from graftcache.backbones.base import BackboneAdapter

BACKBONES: dict[str, str] = {
    "smolvla": "graftcache.backbones.smolvla:SmolVLAAdapter",
    "pi05": "graftcache.backbones.pi05:PI05Adapter",
}


def get_backbone(name: str) -> type[BackboneAdapter]:
    """The adapter class registered under `name`."""
    try:
        module, attr = BACKBONES[name].split(":")
    except KeyError:
        raise BackboneError(f"unknown backbone {name!r}; choose one of {', '.join(BACKBONES)}") from None
    return getattr(importlib.import_module(module), attr)


def load_backbone(name: str, source: str | Path, *, device: str = "cpu", dataset_stats: dict | None = None,
                  tiny: TinySpec | None = None) -> BackboneAdapter:
    """Load backbone `name` from `source` ("tiny", a hub id in the HF cache, or a checkpoint folder)."""
    return get_backbone(name).load(source, device=device, dataset_stats=dataset_stats, tiny=tiny)


__all__ = ["BACKBONES", "TinySpec", "get_backbone", "load_backbone"]
