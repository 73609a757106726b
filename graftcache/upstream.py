"""The upstream releases graftcache reaches past the public API of, and the one check of them.

graftcache calls into lerobot's insides in two houses: the rollout's seam (graftcache.rollout.seam: lerobot's LIBERO
env and lerobot-eval, hf-libero's env, robosuite's MjSim) and the backbone adapters (graftcache/backbones/<name>/:
private methods of lerobot's VLA policies and processors, which they call to feed a graft). Those insides move
between releases without notice, so each house checks, before it reaches, that the installed release is the one its
code was read in (WRITTEN_AGAINST): another is refused in one line naming both and the pin, instead of failing deep in
a fit or an episode with a traceback. One table for both houses, so an upgrade is one edit here and in pyproject.toml.
"""

from __future__ import annotations

from collections.abc import Sequence
from importlib import metadata

from graftcache.errors import GraftcacheError

#: the releases whose insides graftcache's reaches were read in (pyproject.toml pins lerobot to the same)
WRITTEN_AGAINST = {"lerobot": "0.6.1", "hf-libero": "0.1.4", "robosuite": "1.4.0"}


def installed(distribution: str) -> str | None:
    """The installed version of `distribution`, None when it is not installed."""
    try:
        return metadata.version(distribution)
    except metadata.PackageNotFoundError:
        return None


def refuse_others(distributions: Sequence[str], reader: str, error: type[GraftcacheError]) -> None:
    """Raise `error`, one line naming `reader` (the code that reaches), both versions and the pin, when any of
    `distributions` is installed at another version than WRITTEN_AGAINST's. One not installed passes: whoever
    imports it names its set-up (graftcache.rollout.simulator_setup.require_simulator; lerobot is a core
    dependency)."""
    other = {name: found for name in distributions
             if (found := installed(name)) not in (None, WRITTEN_AGAINST[name])}
    if other:
        written = ", ".join(f"{name} {WRITTEN_AGAINST[name]}" for name in other)
        found = ", ".join(f"{name} {version}" for name, version in other.items())
        pins = " ".join(f"{name}=={WRITTEN_AGAINST[name]}" for name in other)
        raise error(f"{reader} was written against {written}, not the installed {found}: pin {pins}")
