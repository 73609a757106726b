"""Finding what a fit names: the encoder's cache, the native tower's cache, the policy checkpoint.

Caches are matched by encoder name and, when `--dataset` is given, by the dataset's content identity
(size + sha256 of its metadata, data and video files, remembered between runs; no decoding), so a cache
extracted from another dataset, or from an earlier version of this one, is never used by mistake: a
cache of the same dataset folder whose content has changed since is refused, naming the first differing
file. The stored width is checked against the registry entry.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

from graftcache.backbones.native import native_name as native_encoder_name
from graftcache.errors import FitError
from graftcache.store import FeatureCache, Root, list_caches

TINY_POLICIES = "policies"
TINY_RECORD = "graftcache_pretrain.json"  # written by pretrain.train_tiny beside the weights


def dataset_fingerprint(dataset: str) -> dict:
    return _dataset_identity(dataset)[0]


def _dataset_identity(dataset: str) -> tuple[dict, str]:
    """The dataset's identity as a cache manifest records it (`dataset_fingerprint`), and its resolved root."""
    from graftcache.datasets import open_dataset

    meta = open_dataset(dataset).meta
    return {"codebase_version": meta.codebase_version, **meta.fingerprint}, str(meta.root)


def find_cache(root: Root, encoder: str, *, dataset: str | None = None, key: str | None = None,
               same_dataset_as: FeatureCache | None = None, for_what: str = "the graft") -> FeatureCache:
    """The one complete cache of `encoder` (for `dataset`), or a clear error saying how to make it."""
    wanted_fp, wanted_root = _dataset_identity(dataset) if dataset else (None, None)
    if same_dataset_as is not None:
        wanted_fp = same_dataset_as.manifest["dataset_fingerprint"]
        wanted_root = same_dataset_as.manifest["dataset"].get("root")
    if key:
        cache = root.open(key)
        if cache.manifest["encoder"]["name"] != encoder:
            raise FitError(f"cache {key} holds encoder {cache.manifest['encoder']['name']!r}, not {encoder!r}")
        candidates = [cache]
    else:
        candidates = [c for c in list_caches(root) if c.manifest["encoder"]["name"] == encoder]
    if wanted_fp is not None:
        named = dataset or same_dataset_as.manifest["dataset"]["source"]
        diffs = {c.key: c.dataset_difference(wanted_fp) for c in candidates}
        other = [c for c in candidates if diffs[c.key] is not None]
        if key and other:
            src = other[0].manifest["dataset"]["source"]
            raise FitError(f"cache {key} was extracted from another dataset ({src}) than the one named "
                           f"({named}); first differing file: {diffs[key]}")
        candidates = [c for c in candidates if c not in other]
        stale = [c for c in other if c.manifest["dataset"].get("root") == wanted_root]
        if stale and not any(c.complete for c in candidates):  # same folder, other content: say which file
            hint = f"graftcache extract --encoder {encoder} --dataset {named}" + \
                (" --policy POLICY" if encoder.endswith("-native") else "")
            raise FitError(f"cache {stale[0].key} of encoder {encoder!r} was extracted from {named} when its content "
                           f"was different; first differing file: {diffs[stale[0].key]}; re-extract: {hint}")
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


def tiny_policies(root: Path, backbone: str, fingerprint: dict) -> list[tuple[Path, dict]]:
    """Natively trained tiny checkpoints of `backbone` for the dataset with `fingerprint`, with their
    training records (`graftcache train-tiny` writes TINY_RECORD beside the weights)."""
    found = []
    for folder in sorted((root / TINY_POLICIES).glob(f"tiny-{backbone}-*")):
        record_file = folder / TINY_RECORD
        if not (folder / "config.json").is_file() or not record_file.is_file():
            continue
        try:
            record = json.loads(record_file.read_text())
        except (OSError, ValueError):
            continue
        if record.get("backbone") == backbone and record.get("dataset_fingerprint") == fingerprint:
            found.append((folder, record))
    return found


def resolve_policy(backbone: str, policy: str, fingerprint: dict, root: Path, dataset_name: str = "DATASET") -> str:
    """`tiny` -> the natively trained tiny checkpoint for the dataset with `fingerprint`; else as given.

    With several tiny checkpoints for the dataset (other steps or seeds), the one trained with the default
    recipe wins (at whichever compute dtype this machine resolved); otherwise the user must pick a folder.
    """
    if policy != "tiny":
        return policy
    from graftcache.pretrain import DEFAULT_TINY_TRAIN

    found = tiny_policies(root, backbone, fingerprint)
    if not found:
        raise FitError(f"no natively trained tiny {backbone} for dataset {dataset_name} in {root / TINY_POLICIES}; "
                       f"run: graftcache train-tiny --backbone {backbone} --dataset {dataset_name}")
    if len(found) > 1:
        def recipe(config: dict) -> dict:  # the compute dtype is resolved per machine, not part of the recipe
            return {k: v for k, v in config.items() if k != "compute_dtype"}

        default = recipe(DEFAULT_TINY_TRAIN.as_dict(backbone))
        found = [(f, r) for f, r in found if recipe(r.get("config", {})) == default] or found
    if len(found) > 1:
        raise FitError(f"several tiny {backbone} checkpoints for dataset {dataset_name}: "
                       f"{', '.join(str(f) for f, _ in found)}; pass one folder as --policy")
    return str(found[0][0])
