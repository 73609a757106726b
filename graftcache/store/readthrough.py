"""Reading a remote cache through a local copy of the objects a fit touches.

`fit --cache s3://...` must not download the whole store. A cache's small objects (every zarr.json, the
index, low-dim and action-stream arrays) are copied on open; feature block files, one per block and array, are
copied the first time a read needs them. Zarr then reads the local copies, and the block checksums are
checked on those bytes as for any cache (graftcache.store.cache), so a damaged remote or local copy is
refused by name. Whole block files are the unit because a block's checksum covers the whole block.

The copies live under `<local cache root>/remote/<sha of the root URL>/<key>/`, shared by later runs;
`fetched_bytes` counts the bytes this process added to the local copies. Reader processes of one fit fetch
independently, so two may download the same block file at once; the first copy in stays (put-if-absent) and only it
is counted, so the counts of a fit's processes add up to what its copies hold.
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from contextlib import AbstractContextManager
from pathlib import Path
from typing import Any

from zarr.abc.store import Store

from graftcache.errors import CacheError
from graftcache.store.roots import LocalRoot, ObjectRoot, Root, cache_root, open_root

MIRROR_DIR = "remote"
FETCH_THREADS = 8  # object-store latency, not bandwidth, bounds one-at-a-time reads of small block files
FEATURES = "features/"


class ReadThroughRoot(Root):
    """A read-only view of an object-store root backed by local copies of what was read."""

    def __init__(self, remote: ObjectRoot, local: Path) -> None:
        self.remote = remote
        self.local = LocalRoot(local / MIRROR_DIR / hashlib.sha256(remote.url.encode()).hexdigest()[:16])
        self.fetched_bytes = 0
        self._listed: dict[str, dict[str, int]] = {}

    @property
    def url(self) -> str:
        return self.remote.url

    def _objects(self, key: str) -> dict[str, int]:
        if key not in self._listed:
            self._listed[key] = self.remote.sizes(f"{key}/")
        return self._listed[key]

    def zarr_store(self, key: str, *, read_only: bool) -> Store:
        small = [rel.split("/", 1)[1] for rel in self._objects(key)
                 if not rel.split("/", 1)[1].startswith(FEATURES) or rel.endswith("zarr.json")]
        self.fetch(key, small)
        return self.local.zarr_store(key, read_only=True)

    def fetch(self, key: str, rels: list[str]) -> None:
        missing = [f"{key}/{r}" for r in rels
                   if f"{key}/{r}" in self._objects(key) and self.local.get_size(f"{key}/{r}") is None]
        with ThreadPoolExecutor(FETCH_THREADS) as threads:
            for size in threads.map(self._copy, missing):
                self.fetched_bytes += size

    def _copy(self, rel: str) -> int:
        data = self.remote.get(rel)
        if data is None:
            raise CacheError(f"{self.remote.url}/{rel}: listed, then gone while reading")
        return len(data) if self.local.put(rel, data, if_absent=True) else 0

    def get(self, rel: str) -> bytes | None:
        return self.remote.get(rel)

    def sizes(self, prefix: str) -> dict[str, int]:
        return self.remote.sizes(prefix)

    def keys(self) -> list[str]:
        return self.remote.keys()

    def put(self, rel: str, data: bytes, *, if_absent: bool = False) -> bool:
        raise CacheError(f"{self.remote.url}/{rel}: read-through roots are read-only")

    def delete(self, rels: list[str]) -> None:
        raise CacheError(f"{self.remote.url}: read-through roots are read-only")

    def writer(self, key: str, on_wait: Callable[[str], None] | None = None) -> AbstractContextManager[Any]:
        raise CacheError(f"{self.remote.url}/{key}: read-through roots are read-only")


def reading_root(explicit: str | Path | None = None) -> Root:
    """The root stage 2 reads: a local folder as it is, an object store through local copies."""
    root = open_root(explicit)
    return ReadThroughRoot(root, cache_root()) if isinstance(root, ObjectRoot) else root
