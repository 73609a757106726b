"""Loaded backbones shared by every cell of one command (fit, sweep, demo).

A backbone is loaded once per (name, policy, device) and handed out reset to its frozen state as loaded
(`BackboneAdapter.reset`: the graft's surgery undone; no weight is written, so none is copied), so a sweep's
cells cost one load per backbone, and cells that are already done load nothing at all. What each load was
grafted as is logged once per kind of graft (`describe`), not once per cell.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

from graftcache.backbones import load_backbone

if TYPE_CHECKING:
    from graftcache.backbones.base import BackboneAdapter
    from graftcache.backbones.surgery import FreezeReport


class LoadedBackbones:
    def __init__(self, log: Callable[[str], None] = print) -> None:
        self._loaded: dict[tuple[str, str, str], BackboneAdapter] = {}
        self._said: dict[int, list[FreezeReport]] = {}  # id of a loaded adapter -> the freeze reports logged of it
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

    def describe(self, adapter: BackboneAdapter, cells: str) -> None:
        """Log which modules of the grafted `adapter` train, for `cells` (who grafted it): its whole freeze report
        the first time a loaded policy is grafted, then only a report not logged of it yet, as what differs from the
        first (a sweep's cells log each kind of graft once, not a report per cell)."""
        report = adapter.freeze_report()
        said = self._said.setdefault(id(adapter), [])
        if not said:
            self.log(f"{adapter.name} as grafted for {cells}, parameters per module (said once per loaded policy; "
                     f"a later graft of it says what differs):\n{report}")
        elif report not in said:
            self.log(f"{adapter.name} as grafted for {cells}: as the report above but {report.changes(said[0])}")
        if report not in said:
            said.append(report)

    @property
    def loads(self) -> int:
        """How many backbones these have loaded (each (name, policy, device) once)."""
        return len(self._loaded)
