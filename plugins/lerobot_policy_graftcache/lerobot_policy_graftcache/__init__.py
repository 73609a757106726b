"""Registers graftcache's exported policy (type `graftcache`) and its processor steps with lerobot on import: what
lerobot's plugin hook does for every installed `lerobot_policy_*` distribution."""

from graftcache.export.configuration_graftcache import GraftcacheConfig
from graftcache.export.processors import BasePostprocessorStep, CellFeaturesStep

__all__ = ["BasePostprocessorStep", "CellFeaturesStep", "GraftcacheConfig"]
