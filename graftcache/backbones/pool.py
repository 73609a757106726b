"""Loaded backbones shared by every cell of a run (fit, sweep, demo).

A backbone is loaded once per (name, policy, device) and handed out reset to its frozen state as loaded
(`BackboneAdapter.reset`: the graft's surgery undone; no weight is written, so none is copied), so a grid
of cells costs one load per backbone, and cells that are already done load nothing at all.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

from graftcache.backbones import load_backbone

if TYPE_CHECKING:
    from graftcache.backbones.base import BackboneAdapter


class BackbonePool:
    def __init__(self, log: Callable[[str], None] = print) -> None:
        self._loaded: dict[tuple[str, str, str], BackboneAdapter] = {}
        self.log = log

    def get(self, name: str, policy: str | Path, device: str) -> BackboneAdapter:
        """The backbone `name` loaded from `policy` on `device`, reset to its state as loaded."""
        key = (name, str(policy), str(device))
        if key not in self._loaded:
            self.log(f"loading backbone {name} from {policy} on {device}")
            self._loaded[key] = load_backbone(name, policy, device=str(device))
        adapter = self._loaded[key]
        adapter.reset()
        return adapter

    @property
    def loads(self) -> int:
        """How many backbones this pool has loaded (each (name, policy, device) once)."""
        return len(self._loaded)
