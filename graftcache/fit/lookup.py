"""Finding the caches a fit names: the encoder's cache and the native tower's cache.

Caches are matched by encoder name and, when `--dataset` is given, by the dataset's content identity
(size + sha256 of its metadata, data and video files, remembered between runs; no decoding), so a cache
extracted from another dataset, or from an earlier version of this one, is never used by mistake: a
cache of the same dataset folder whose content has changed since is refused, naming the first differing
file. The stored width is checked against the registry entry.
"""

from __future__ import annotations

from pathlib import Path

from graftcache.backbone_registry import NATIVE_SUFFIX
from graftcache.datasets import open_dataset
from graftcache.encoders import get_spec
from graftcache.errors import FitError
from graftcache.store import FeatureCache, Root, list_caches, open_root
from graftcache.store.key import check_key


def dataset_identity(dataset: str) -> dict:
    """The dataset's identity as a cache manifest records it (`dataset_identity`)."""
    return open_dataset(dataset).meta.identity


def _dataset_identity(dataset: str) -> tuple[dict, str]:
    """The dataset's identity and its resolved root."""
    meta = open_dataset(dataset).meta
    return meta.identity, str(meta.root)


def find_cache(root: Root | str | Path, encoder: str, *, dataset: str | None = None, key: str | None = None,
               same_dataset_as: FeatureCache | None = None, for_what: str = "the graft") -> FeatureCache:
    """The one complete cache of `encoder` (for `dataset`), or a clear error saying how to make it."""
    if key:
        check_key(key)  # a key is a name: refused before the dataset is hashed or the root read
    root = open_root(root)
    wanted_identity, wanted_root = _dataset_identity(dataset) if dataset else (None, None)
    if same_dataset_as is not None:
        wanted_identity = same_dataset_as.manifest.dataset_identity
        wanted_root = same_dataset_as.manifest.dataset.root
    if key:
        cache = FeatureCache.in_root(root, key)
        if cache.manifest.encoder_name != encoder:
            raise FitError(f"cache {key} holds encoder {cache.manifest.encoder_name!r}, not {encoder!r}")
        candidates = [cache]
    else:
        candidates = [c for c in list_caches(root) if c.manifest.encoder_name == encoder]
    if wanted_identity is not None:
        named = dataset or same_dataset_as.manifest.dataset.source
        diffs = {c.key: c.dataset_difference(wanted_identity) for c in candidates}
        other = [c for c in candidates if diffs[c.key] is not None]
        if key and other:
            src = other[0].manifest.dataset.source
            raise FitError(f"cache {key} was extracted from another dataset ({src}) than the one named "
                           f"({named}); first differing file: {diffs[key]}")
        candidates = [c for c in candidates if c not in other]
        stale = [c for c in other if c.manifest.dataset.root == wanted_root]
        if stale and not any(c.complete for c in candidates):  # same folder, other content: say which file
            hint = f"graftcache extract --encoder {encoder} --dataset {named}" + \
                (" --policy POLICY" if encoder.endswith(NATIVE_SUFFIX) else "")
            raise FitError(f"cache {stale[0].key} of encoder {encoder!r} was extracted from {named} when its content "
                           f"was different; first differing file: {diffs[stale[0].key]}; re-extract: {hint}")
    complete = [c for c in candidates if c.complete]
    if not complete:
        where = f" for dataset {dataset}" if dataset else ""
        hint = f"graftcache extract --encoder {encoder} --dataset {dataset or 'PATH'}"
        if encoder.endswith(NATIVE_SUFFIX):
            hint += " --policy POLICY"
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
    enc = cache.manifest.encoder
    name = enc["name"]
    try:
        # width 0: measured per loaded model (native towers), so the manifest's own spec is the reference
        spec_width = get_spec(name).width or enc["width"]
    except Exception:
        spec_width = enc["width"]  # parametric entries: the manifest's own spec is the reference
    for path, shape in cache.layout["arrays"].items():
        if path.rsplit("/", 1)[-1] in cache.manifest.extras:
            continue
        if shape[-1] != spec_width:
            raise FitError(f"cache {cache.key}: {path} is {shape[-1]} wide but encoder {name!r} "
                           f"is {spec_width} wide in the registry")
