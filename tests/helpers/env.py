"""The environment every test process runs in, in one place: conftest.py sets it for this process, and the
Ray fixture (tests/fixtures/ray_cluster.py) hands it to the Ray workers, which see no monkeypatched variable."""

from __future__ import annotations

from pathlib import Path

#: Offline before anything imports huggingface_hub: a missing model fails at once instead of retrying.
OFFLINE = {"HF_HUB_OFFLINE": "1", "HF_DATASETS_OFFLINE": "1", "TRANSFORMERS_OFFLINE": "1"}


def isolated_homes(root: Path) -> dict[str, str]:
    """Every cache a test could touch (graftcache, HF hub, lerobot) under one per-session temp dir."""
    return {"GRAFTCACHE_HOME": str(root / "graftcache_home"), "HF_HOME": str(root / "hf_home"),
            "HF_HUB_CACHE": str(root / "hf_home" / "hub"), "HF_LEROBOT_HOME": str(root / "hf_home" / "lerobot")}
