"""Finding what a fit names: the encoder's cache, the native tower's cache, the policy checkpoint.

Caches are matched by encoder name and, when `--dataset` is given, by the dataset's content
fingerprint (meta files only, no decoding), so a cache extracted from another dataset is never
used by mistake. The stored width is checked against the registry entry.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

from graftcache.backbones.native import native_name as native_encoder_name
from graftcache.errors import FitError
from graftcache.store import FeatureCache, list_caches

TINY_POLICIES = "policies"


def dataset_fingerprint(dataset: str) -> dict:
    from graftcache.datasets import open_dataset

    meta = open_dataset(dataset).meta
    return {"codebase_version": meta.codebase_version, **meta.fingerprint}


def find_cache(root: Path, encoder: str, *, dataset: str | None = None, key: str | None = None,
               same_dataset_as: FeatureCache | None = None, for_what: str = "the graft") -> FeatureCache:
    """The one complete cache of `encoder` (for `dataset`), or a clear error saying how to make it."""
    wanted_fp = dataset_fingerprint(dataset) if dataset else None
    if same_dataset_as is not None:
        wanted_fp = same_dataset_as.manifest["dataset_fingerprint"]
    if key:
        cache = FeatureCache(root / key)
        if cache.manifest["encoder"]["name"] != encoder:
            raise FitError(f"cache {key} holds encoder {cache.manifest['encoder']['name']!r}, not {encoder!r}")
        candidates = [cache]
    else:
        candidates = [c for c in list_caches(root) if c.manifest["encoder"]["name"] == encoder]
    if wanted_fp is not None:
        other = [c for c in candidates if c.manifest["dataset_fingerprint"] != wanted_fp]
        if key and other:
            src = other[0].manifest["dataset"]["source"]
            raise FitError(f"cache {key} was extracted from another dataset ({src}) than the one named "
                           f"({dataset or same_dataset_as.manifest['dataset']['source']})")
        candidates = [c for c in candidates if c not in other]
    complete = [c for c in candidates if c.complete]
    if not complete:
        where = f" for dataset {dataset}" if dataset else ""
        hint = f"graftcache extract --encoder {encoder} --dataset {dataset or 'PATH'}"
        if encoder.endswith("-native"):
            hint += f" --policy POLICY --grids 8x8"
        state = " (an incomplete one exists: rerun extract to finish it)" if candidates else ""
        raise FitError(f"no complete cache of encoder {encoder!r}{where} in {root}{state}, needed for {for_what}; "
                       f"run: {hint}")
    if len(complete) > 1:
        keys = ", ".join(c.key for c in complete)
        raise FitError(f"several caches of encoder {encoder!r} match ({keys}); choose one with --cache-key")
    cache = complete[0]
    _check_width(cache)
    return cache


def _check_width(cache: FeatureCache) -> None:
    """The stored grids must be as wide as the registry entry says (a stale or foreign cache is not)."""
    from graftcache.encoders import get_spec

    enc = cache.manifest["encoder"]
    name = enc["name"]
    try:
        # width 0: measured per loaded model (native towers), so the manifest's own spec is the reference
        spec_width = get_spec(name).width or enc["width"]
    except Exception:
        spec_width = enc["width"]  # parametric entries: the manifest's own spec is the reference
    for path, shape in cache.layout["arrays"].items():
        if path.rsplit("/", 1)[-1] in cache.manifest.get("extras", {}):
            continue
        if shape[-1] != spec_width:
            raise FitError(f"cache {cache.key}: {path} is {shape[-1]} wide but encoder {name!r} "
                           f"is {spec_width} wide in the registry")


def tiny_policy_dir(root: Path, backbone: str, fingerprint: dict, train_config: dict) -> Path:
    """Folder of a natively trained tiny backbone, keyed by dataset content and training recipe."""
    blob = json.dumps({"fp": fingerprint, "cfg": train_config}, sort_keys=True, default=str).encode()
    return root / TINY_POLICIES / f"tiny-{backbone}-{hashlib.sha256(blob).hexdigest()[:12]}"


def resolve_policy(backbone: str, policy: str, fingerprint: dict, root: Path, dataset_name: str = "DATASET") -> str:
    """`tiny` -> the natively trained tiny checkpoint for the dataset with `fingerprint`; else as given."""
    if policy != "tiny":
        return policy
    from graftcache.pretrain import DEFAULT_TINY_TRAIN

    folder = tiny_policy_dir(root, backbone, fingerprint, DEFAULT_TINY_TRAIN.as_dict(backbone))
    if not (folder / "config.json").exists():
        raise FitError(f"no natively trained tiny {backbone} for dataset {dataset_name} (looked in {folder}); "
                       f"run: graftcache train-tiny --backbone {backbone} --dataset {dataset_name}")
    return str(folder)
