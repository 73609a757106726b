"""Installed versions as a test needs them: importlib.metadata answering made-up versions for some distributions, or
none for one, the real answer for every other (graftcache.upstream asks it)."""

from __future__ import annotations

from importlib import metadata

import pytest


def installed_as(monkeypatch: pytest.MonkeyPatch, **versions: str) -> None:
    """importlib.metadata.version answering `versions` (distribution names with _ for -) for those distributions."""
    real = metadata.version
    faked = {name.replace("_", "-"): version for name, version in versions.items()}
    monkeypatch.setattr(metadata, "version", lambda name: faked.get(name) or real(name))


def not_installed(monkeypatch: pytest.MonkeyPatch, distribution: str) -> None:
    """importlib.metadata.version raising PackageNotFoundError for `distribution`, as for one never installed."""
    real = metadata.version

    def version(name: str) -> str:
        if name == distribution:
            raise metadata.PackageNotFoundError(name)
        return real(name)

    monkeypatch.setattr(metadata, "version", version)
