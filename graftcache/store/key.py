"""Cache identity: what changes the stored numbers, and the key derived from it.

The key hashes exactly the fields that change the numbers (dataset content identity, episode
subset, encoder recipe, weights, grids, dtypes, cameras, cache format) and nothing that does not
(batch size, worker count, device, cache folder, dataset path). Two users who extract the same
dataset with the same encoder therefore land on the same key and can share the folder.

The dataset part (`dataset_identity`) is the dataset's content identity: size and sha256 of its
metadata files and of every data parquet and video the episodes use (graftcache.datasets.identity), so a
dataset edited under unchanged metadata gets another key. `compare_identity` names the first file in
which a recorded identity differs from a dataset's current one, for every place that uses an existing
cache with a dataset (fit --dataset, resuming an extraction, sharing).

A key is a name, never a path: `check_key` (the grammar, defined here once) is applied to every key a user
or a caller hands in, before any I/O, so `../x`, `/abs/x` or `a/b` never reach a root. A cache is only the
cache of the key its folder is named by when its manifest hashes to that key (graftcache.store.cache), so a
folder copied or renamed by hand is not taken for another cache.
"""

from __future__ import annotations

import json
import re
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from graftcache.errors import CacheError
from graftcache.hashing import sha256_json

#: The longest encoder-name part of a key: a key, its lock and its lease stay one file name (<= 255 bytes).
NAME_MAX = 128
#: What a key is: the encoder's name in file-name-safe characters (not starting with '.', '+' or '-'), '-',
#: and 16 lowercase hex digits of the identity hash. One path component, never '.' or '..', never hidden.
KEY = re.compile(rf"[A-Za-z0-9_][A-Za-z0-9_.+-]{{0,{NAME_MAX - 1}}}-[0-9a-f]{{16}}")
#: A writer's lock/lease name: a key, or one shard of it (`<key>.shard-<i>-of-<N>`, graftcache.extract).
WRITER = re.compile(rf"(?P<key>{KEY.pattern})(\.shard-[0-9]+-of-[0-9]+)?")
_UNSAFE = re.compile(r"[^A-Za-z0-9_.+-]")


class RefusedPlace(CacheError):
    """A place graftcache never reads through, replaces or deletes: a path given as a key, a symbolic link in
    a root, another cache stored under a key's name. Never taken for an absent or unfinished cache."""

# Manifest fields that make up the identity; everything else in the manifest is provenance only.
IDENTITY_FIELDS = (
    "format_version",
    "dataset_identity",
    "episodes",
    "frame_stride",
    "cameras",
    "encoder",
    "weights_sha256",
    "grids",
    "extras",
    "storage_dtype",
    "compute_dtype",
)


def identity_of(manifest: Mapping[str, Any], fields: tuple[str, ...] = IDENTITY_FIELDS) -> dict[str, Any]:
    """The identity sub-dict of a stored manifest (canonical JSON types); `fields`: the identity fields' names
    in the manifest's format (graftcache.store.manifest.stored_key names those of older formats)."""
    return json.loads(json.dumps({k: manifest[k] for k in fields}, sort_keys=True, default=str))


def cache_key(manifest: Mapping[str, Any], fields: tuple[str, ...] = IDENTITY_FIELDS) -> str:
    """`<encoder-name>-<16 hex>`: readable prefix + sha256 of the canonical identity JSON. Characters a file
    name should not hold (':' and '/' of `timm:`/`hf:<folder>` names, spaces) become '_': keys match `KEY`."""
    name = _UNSAFE.sub("_", str(manifest["encoder"]["name"]))[:NAME_MAX]
    if name[:1] in ("", ".", "+", "-"):  # '.x' would be hidden, '-x' reads as a flag
        name = f"_{name}"[:NAME_MAX]
    return f"{name}-{sha256_json(identity_of(manifest, fields), compact=True)[:16]}"


def check_key(key: object) -> str:
    """`key` when it is a cache key, else a one-line CacheError: keys name caches inside a root and are never
    paths (`../victim`, `/abs/KEY` and `a/b` would read, write or delete outside it)."""
    if isinstance(key, str) and KEY.fullmatch(key):
        return key
    raise RefusedPlace(f"{key!r} is not a cache key: a key is a name, <encoder>-<16 hex digits> as "
                       "`graftcache ls` lists it (e.g. resnet18-0123456789abcdef), never a path")


def check_writer(name: str) -> str:
    """`name` when it names a writer of a key (the key, or one shard of it), else CacheError."""
    if not WRITER.fullmatch(name):
        check_key(name.split(".shard-", 1)[0])  # names the key part when that is what is wrong
        raise RefusedPlace(f"{name!r} is not a writer of a cache key (<key> or <key>.shard-<i>-of-<N>)")
    return name


@dataclass(frozen=True)
class IdentityDifference:
    """The first place where two dataset identities differ: a file (or field) and how."""

    path: str
    detail: str

    def __str__(self) -> str:
        return f"{self.path} ({self.detail})"


def compare_identity(recorded: Mapping[str, Any], current: Mapping[str, Any]) -> IdentityDifference | None:
    """None when `recorded` (e.g. a cache manifest's `dataset_identity`) equals `current`; otherwise
    the first differing file (metadata files first, then data and videos in path order)."""
    recorded, current = _canonical(recorded), _canonical(current)
    if recorded == current:
        return None
    was, now = recorded.get("files", {}), current.get("files", {})
    for rel in _ordered({**was, **now}):
        if rel not in now:
            return IdentityDifference(rel, "recorded, not in the dataset now")
        if rel not in was:
            return IdentityDifference(rel, "in the dataset now, not recorded")
        if was[rel] != now[rel]:
            return _changed(rel, was[rel], now[rel])
    for field in sorted(set(recorded) | set(current)):
        if field != "files" and recorded.get(field) != current.get(field):
            return IdentityDifference(field, f"{recorded.get(field)} recorded, {current.get(field)} now")
    return None


def _canonical(identity: Mapping[str, Any]) -> dict[str, Any]:
    return json.loads(json.dumps(dict(identity), sort_keys=True, default=str))


def _ordered(files: Mapping[str, Any]) -> list[str]:
    """Metadata files first, then everything else, each in path order."""
    return sorted(files, key=lambda rel: (not rel.startswith("meta/"), rel))


def _changed(rel: str, was: Mapping[str, Any], now: Mapping[str, Any]) -> IdentityDifference:
    if "size" in was and was.get("size") != now.get("size"):
        return IdentityDifference(rel, f"size {was['size']} recorded, {now.get('size')} now")
    return IdentityDifference(rel, f"sha256 {str(was.get('sha256'))[:12]}... recorded, "
                                   f"{str(now.get('sha256'))[:12]}... now")
