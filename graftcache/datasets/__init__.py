"""LeRobot dataset reading: metadata, per-episode frames and the low-dim table, without lerobot's
dataset class in the hot path (see source.py for why and ARCHITECTURE.md for the contract).

The names below are imported on first use (graftcache.lazy), so that `graftcache.datasets.suites`, which is
data, imports without the table and video libraries the readers need (polars, PyAV): the suite rule of every
request reads it, also where those libraries are not installed (benchmarks/gpu_check.py on a GPU machine)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from graftcache.lazy import import_string

if TYPE_CHECKING:
    from graftcache.datasets.meta import DatasetMeta, EpisodeMeta
    from graftcache.datasets.source import LeRobotSource, open_dataset
    from graftcache.datasets.suites import suite_of

_EXPORTS = {
    "DatasetMeta": "graftcache.datasets.meta:DatasetMeta",
    "EpisodeMeta": "graftcache.datasets.meta:EpisodeMeta",
    "LeRobotSource": "graftcache.datasets.source:LeRobotSource",
    "open_dataset": "graftcache.datasets.source:open_dataset",
    "suite_of": "graftcache.datasets.suites:suite_of",
}


def __getattr__(name: str) -> Any:
    if name not in _EXPORTS:
        raise AttributeError(f"module 'graftcache.datasets' has no attribute {name!r}")
    return import_string(_EXPORTS[name])


__all__ = ["DatasetMeta", "EpisodeMeta", "LeRobotSource", "open_dataset", "suite_of"]
