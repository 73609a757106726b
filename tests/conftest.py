"""Test-wide settings: fully offline, caches in temporary folders, no GPU assumptions.

Every fixture is available to every test module by argument: the ones shared across modules live in the
plugins below (tests/fixtures/), plain helpers in tests/helpers/ (imported normally).
"""

from __future__ import annotations

import os

from helpers.env import OFFLINE, isolated_homes

os.environ.update(OFFLINE)  # before anything imports huggingface_hub
os.environ.setdefault("TOKENIZERS_PARALLELISM", "false")

import pytest  # noqa: E402

pytest_plugins = ("fixtures.datasets", "fixtures.torch_threads", "fixtures.ray_cluster", "fixtures.s3")


@pytest.fixture(autouse=True)
def _isolated_homes(tmp_path_factory: pytest.TempPathFactory, monkeypatch: pytest.MonkeyPatch) -> None:
    """Point every cache a test could touch (graftcache, HF hub, lerobot) at a per-session temp dir."""
    for name, value in isolated_homes(tmp_path_factory.getbasetemp()).items():
        monkeypatch.setenv(name, value)
