"""Backbone registry: a name from graftcache.backbone_registry -> adapter class (see base.BackboneAdapter).

Each backbone is a folder of this package (graftcache.backbone_registry.BACKBONES lists them); its adapter class is the
one class its `adapter.py` defines with that `name`. Adapters are imported on first use: importing lerobot costs
seconds, which commands such as `graftcache ls` should not pay. Adapters call private methods of lerobot's policies
and processors, read in one lerobot release (graftcache.upstream.WRITTEN_AGAINST): another installed release is
refused before an adapter is imported, in one line, rather than by an adapter failing in a traceback mid-fit.
"""

from __future__ import annotations

from importlib import import_module
from pathlib import Path
from typing import TYPE_CHECKING

from graftcache.backbone_registry import BACKBONES, backbone_module
from graftcache.errors import BackboneError
from graftcache.upstream import refuse_others

if TYPE_CHECKING:
    from graftcache.backbones.base import BackboneAdapter
    from graftcache.backbones.spec import BackboneSpec
    from graftcache.backbones.tiny import TinyBuild


def get_backbone(name: str) -> type[BackboneAdapter]:
    """The adapter class registered under `name`: the class `graftcache.backbones.<name>.adapter` defines whose
    `name` is `name` (exactly one), once the installed lerobot is the release the adapters were read in."""
    if name not in BACKBONES:
        raise BackboneError(f"unknown backbone {name!r}; choose one of {', '.join(BACKBONES)}")
    refuse_others(("lerobot",), f"graftcache/backbones/{name}/", BackboneError)
    module = import_module(BACKBONES[name])
    found = [v for v in vars(module).values()
             if isinstance(v, type) and v.__module__ == module.__name__ and v.__dict__.get("name") == name]
    if len(found) != 1:
        raise BackboneError(f"{module.__name__} defines {len(found)} adapter classes named {name!r}, not one")
    return found[0]


def registered_spec(name: str) -> BackboneSpec | None:
    """The spec of backbone `name`, its folder's `spec.py` (data: no adapter, torch or lerobot is imported), or None
    for a name outside the registry (a results table typed in from a paper may name any backbone). What tables of all
    backbones read: their labels (graftcache.analysis.table.backbone_label), their released sizes
    (graftcache.analysis.ladder)."""
    return import_module(backbone_module(name, "spec")).SPEC if name in BACKBONES else None


def load_backbone(name: str, source: str | Path, *, device: str = "cpu", dataset_stats: dict | None = None,
                  tiny: TinyBuild | None = None) -> BackboneAdapter:
    """Load backbone `name` from `source` ("tiny", a hub id in the HF cache, or a checkpoint folder)."""
    return get_backbone(name).load(source, device=device, dataset_stats=dataset_stats, tiny=tiny)


__all__ = ["BACKBONES", "get_backbone", "load_backbone", "registered_spec"]
