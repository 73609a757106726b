"""LeRobot dataset reading: metadata, per-episode frames and the low-dim table, without lerobot's
dataset class in the hot path (see source.py for why and ARCHITECTURE.md for the contract)."""

from graftcache.datasets.meta import DatasetMeta, EpisodeMeta
from graftcache.datasets.source import LeRobotSource, open_dataset
from graftcache.datasets.suites import suite_of

__all__ = ["DatasetMeta", "EpisodeMeta", "LeRobotSource", "open_dataset", "suite_of"]
