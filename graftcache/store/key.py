"""Cache identity: what changes the stored numbers, and the key derived from it.

The key hashes exactly the fields that change the numbers (dataset content fingerprint, episode
subset, encoder recipe, weights, grids, dtypes, cameras, cache format) and nothing that does not
(batch size, worker count, device, cache folder, dataset path). Two users who extract the same
dataset with the same encoder therefore land on the same key and can share the folder.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping
from typing import Any

FORMAT_VERSION = 1

# Manifest fields that make up the identity; everything else in the manifest is provenance only.
IDENTITY_FIELDS = (
    "format_version",
    "dataset_fingerprint",
    "episodes",
    "cameras",
    "encoder",
    "weights_sha256",
    "grids",
    "extras",
    "dtype",
    "compute_dtype",
)


def identity_of(manifest: Mapping[str, Any]) -> dict[str, Any]:
    """The identity sub-dict of a manifest (canonical JSON types)."""
    return json.loads(json.dumps({k: manifest[k] for k in IDENTITY_FIELDS}, sort_keys=True, default=str))


def cache_key(manifest: Mapping[str, Any]) -> str:
    """`<encoder-name>-<16 hex>`: readable prefix + sha256 of the canonical identity JSON."""
    blob = json.dumps(identity_of(manifest), sort_keys=True, separators=(",", ":")).encode()
    name = str(manifest["encoder"]["name"]).replace(":", "_").replace("/", "_")
    return f"{name}-{hashlib.sha256(blob).hexdigest()[:16]}"
