"""Where the Hugging Face hub cache is, read from the environment at call time.

huggingface_hub reads these variables once, at import; graftcache's own offline lookups (datasets,
encoder weights, policy checkpoints) read them when called, so tests and CLIs can redirect them, and
all of them agree on one order: `$HF_HUB_CACHE` (or the legacy `$HUGGINGFACE_HUB_CACHE`), else
`$HF_HOME/hub`, else `$XDG_CACHE_HOME/huggingface/hub`, else `~/.cache/huggingface/hub`.
"""

from __future__ import annotations

import os
from pathlib import Path


def hf_home() -> Path:
    """`$HF_HOME`, else `$XDG_CACHE_HOME/huggingface`, else `~/.cache/huggingface` (huggingface_hub's rule)."""
    if os.getenv("HF_HOME"):
        return Path(os.environ["HF_HOME"]).expanduser()
    return Path(os.getenv("XDG_CACHE_HOME") or "~/.cache").expanduser() / "huggingface"


def hub_cache() -> Path:
    """`$HF_HUB_CACHE` (or the legacy `$HUGGINGFACE_HUB_CACHE`), else `<hf_home>/hub`."""
    env = os.getenv("HF_HUB_CACHE") or os.getenv("HUGGINGFACE_HUB_CACHE")
    return Path(env).expanduser() if env else hf_home() / "hub"


def repo_dir(repo_id: str, kind: str = "models", cache: Path | None = None) -> Path:
    """A repo's folder in the hub cache, e.g. `<hub cache>/models--ORG--NAME` (kind "models" or "datasets")."""
    return (cache or hub_cache()) / f"{kind}--{repo_id.replace('/', '--')}"
