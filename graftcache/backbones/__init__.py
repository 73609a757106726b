"""Backbone registry: a name from graftcache.backbone_table -> adapter class (see base.BackboneAdapter).

Adapters are imported on first use: importing lerobot costs ~5 s, which commands such as
`graftcache ls` should not pay.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from graftcache.backbone_table import BACKBONES
from graftcache.backbones.tiny import TinySpec
from graftcache.errors import BackboneError
from graftcache.lazy import import_string

if TYPE_CHECKING:
    from graftcache.backbones.base import BackboneAdapter

def get_backbone(name: str) -> type[BackboneAdapter]:
    """The adapter class registered under `name`."""
    if name not in BACKBONES:
        raise BackboneError(f"unknown backbone {name!r}; choose one of {', '.join(BACKBONES)}")
    return import_string(BACKBONES[name])


def load_backbone(name: str, source: str | Path, *, device: str = "cpu", dataset_stats: dict | None = None,
                  tiny: TinySpec | None = None) -> BackboneAdapter:
    """Load backbone `name` from `source` ("tiny", a hub id in the HF cache, or a checkpoint folder)."""
    return get_backbone(name).load(source, device=device, dataset_stats=dataset_stats, tiny=tiny)


__all__ = ["BACKBONES", "TinySpec", "get_backbone", "load_backbone"]
