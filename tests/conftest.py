"""Test-wide settings: fully offline, caches in temporary folders, no GPU assumptions.

Every fixture is available to every test module by argument: the ones shared across modules live in the
plugins below (tests/fixtures/), plain helpers in tests/helpers/ (imported normally).
"""

from __future__ import annotations

import os

# Offline before anything imports huggingface_hub: a missing model fails at once instead of retrying.
os.environ["HF_HUB_OFFLINE"] = "1"
os.environ["HF_DATASETS_OFFLINE"] = "1"
os.environ["TRANSFORMERS_OFFLINE"] = "1"
os.environ.setdefault("TOKENIZERS_PARALLELISM", "false")

import pytest  # noqa: E402

pytest_plugins = ("fixtures.datasets", "fixtures.torch_threads")


@pytest.fixture(autouse=True)
def _isolated_homes(tmp_path_factory: pytest.TempPathFactory, monkeypatch: pytest.MonkeyPatch) -> None:
    """Point every cache a test could touch (graftcache, HF hub, lerobot) at a per-session temp dir."""
    root = tmp_path_factory.getbasetemp()
    monkeypatch.setenv("GRAFTCACHE_HOME", str(root / "graftcache_home"))
    monkeypatch.setenv("HF_HOME", str(root / "hf_home"))
    monkeypatch.setenv("HF_HUB_CACHE", str(root / "hf_home" / "hub"))
    monkeypatch.setenv("HF_LEROBOT_HOME", str(root / "hf_home" / "lerobot"))
