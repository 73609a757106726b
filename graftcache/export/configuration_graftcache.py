"""The exported cell's lerobot config: policy type `graftcache` (lerobot's plugin hook imports this module through
the `lerobot_policy_graftcache` distribution; lerobot finds the policy class in the sibling modeling_ module)."""

from __future__ import annotations

from dataclasses import dataclass, field

from lerobot.configs.policies import PreTrainedConfig
from lerobot.optim.optimizers import AdamWConfig

POLICY_TYPE = "graftcache"
#: The export folder's format: 3 records a dose cell's level and seed (`dose`, `dose_seed`) and carries its feature
#: spread (graftcache.fit.dose.SPREAD_FILE); 2 carried the cell's cameras in its preprocessor (relocatable); 1, which
#: config.json files without the field are, named the export's absolute path there instead.
EXPORT_FORMAT = 3


@PreTrainedConfig.register_subclass(POLICY_TYPE)
@dataclass
class GraftcacheConfig(PreTrainedConfig):
    """Everything that identifies the cell an export runs; the numbers live beside it (manifest, projector)."""

    run_id: str = ""
    backbone: str = ""
    base_policy: str = ""             # hub id or checkpoint folder (absolute), loaded with its own processors
    cache_key: str = ""
    encoder: str = ""
    control: str = "none"
    pool_grid: str = ""               # the grid features are pooled to ("8x8")
    cameras: dict[str, str] = field(default_factory=dict)  # policy camera -> the cache (and simulator) camera
    lora_rank: int = 0
    num_denoise_steps: int | None = None
    compute_dtype: str = "fp32"       # the cell's, as its row records it
    n_action_steps: int = 1           # actions executed per predicted chunk (the base policy's own setting)
    accept_numerics_drift: bool = False
    dose: float | None = None         # a noise-A cell's level A (graftcache/fit/dose.py); None for every other control
    dose_seed: int | None = None      # the cell's seed, which seeds each frame's dose noise with the frame's key
    export_format: int = 1            # EXPORT_FORMAT for every export written now; absent (1) in older ones

    @property
    def observation_delta_indices(self) -> None:
        return None

    @property
    def action_delta_indices(self) -> None:
        return None

    @property
    def reward_delta_indices(self) -> None:
        return None

    def get_optimizer_preset(self) -> AdamWConfig:
        """Exports are evaluated, never trained (lerobot asks every config for a preset)."""
        return AdamWConfig()

    def get_scheduler_preset(self) -> None:
        return None

    def validate_features(self) -> None:
        """The features were written by the export from the base policy's own; nothing to derive."""
