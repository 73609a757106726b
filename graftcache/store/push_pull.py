"""push / pull: copy one complete cache between two roots (local folders or object stores), verified.

Protocol, the same in both directions and on every store:
1. The key must be a key (graftcache.store.key.check_key, before any I/O) and the source complete and stored
   under its own key. A destination folder of that name holding another cache (its manifest hashes to another
   key) is refused; a destination cache that is complete and verifies is left alone (nothing copied); a
   complete one with damaged objects loses them and is copied again.
2. Under the destination's writer lock/lease, the source's zarr.json is written with `complete: false`
   first (so the destination reads as an incomplete cache, never as a finished one), then every other
   object the destination lacks (or holds at another size) is copied whole; objects the source does not
   have are removed. A copy killed at any point therefore resumes: present objects are never re-sent.
3. Every block and static array at the destination is re-read and compared with the source's checksums.
   Damaged objects are deleted at the destination (a rerun fetches them again) and the copy fails naming
   the first bad block; only a destination that verified gets the source's zarr.json with `complete: true`,
   written last in one put.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

from graftcache.errors import CacheError
from graftcache.store.cache import FeatureCache
from graftcache.store.key import RefusedPlace, check_key
from graftcache.store.roots import GROUP_META, Root

COPY_THREADS = 8


@dataclass(frozen=True)
class Transfer:
    key: str
    objects: int        # objects copied by this call
    bytes: int          # bytes copied by this call
    already_there: int  # objects a previous, interrupted copy had left at the destination
    skipped: bool       # the destination was complete and verified: nothing copied


def copy_cache(src_root: Root, dst_root: Root, key: str, log: Callable[[str], None] = print) -> Transfer:
    src = FeatureCache.in_root(src_root, check_key(key))
    if not src.complete:
        raise CacheError(f"cache {src.path} is not complete; only complete caches are pushed or pulled")
    existing = _existing(dst_root, key)
    if existing is not None:
        if existing.complete:
            damaged = existing.damage(existing.attrs["checksums"])
            if not damaged:
                log(f"{key}: already complete and verified at {dst_root}")
                return Transfer(key, 0, 0, 0, True)
            log(f"{key}: {len(damaged)} damaged object(s) at {dst_root}, first: {damaged[0][1]}; copying them again")
            _drop(dst_root, key, damaged)
    final_meta = src_root.get(f"{key}/{GROUP_META}")
    pending = json.loads(final_meta)
    pending["attributes"]["complete"] = False
    with dst_root.writer(key, on_wait=lambda who: log(f"waiting: {key} at {dst_root} is being written by {who}")) \
            as held:
        dst_root.put(f"{key}/{GROUP_META}", json.dumps(pending, indent=2).encode())
        wanted = {rel: size for rel, size in src_root.sizes(f"{key}/").items() if rel != f"{key}/{GROUP_META}"}
        have = {rel: size for rel, size in dst_root.sizes(f"{key}/").items() if rel != f"{key}/{GROUP_META}"}
        dst_root.delete([rel for rel in have if rel not in wanted])
        todo = sorted(rel for rel, size in wanted.items() if have.get(rel) != size)
        if len(todo) < len(wanted):
            log(f"{key}: resuming, {len(wanted) - len(todo)} of {len(wanted)} objects already at {dst_root}")

        def copy(rel: str) -> int:
            data = src_root.get(rel)
            if data is None:
                raise CacheError(f"{src_root.url}/{rel}: listed, then gone while copying")
            dst_root.put(rel, data)
            return len(data)

        with ThreadPoolExecutor(COPY_THREADS) as threads:
            copied = sum(threads.map(copy, todo))
        damage = FeatureCache.in_root(dst_root, key).damage(src.attrs["checksums"])
        if damage:
            _drop(dst_root, key, damage)
            raise CacheError(f"copy of {key} from {src_root} to {dst_root} failed verification: {damage[0][1]}"
                             + (f" (and {len(damage) - 1} more)" if len(damage) > 1 else "")
                             + f"; the destination stays incomplete; check the source: graftcache verify {key} "
                               f"--cache {src_root}")
        held.check()
        dst_root.put(f"{key}/{GROUP_META}", final_meta)  # complete, published last
    log(f"{key}: copied {len(todo)} objects ({copied / 2**20:.1f} MiB) from {src_root} to {dst_root}, verified")
    return Transfer(key, len(todo), copied, len(wanted) - len(todo), False)


def _drop(root: Root, key: str, damage: list[tuple[str, str]]) -> None:
    """Delete damaged block files and static-array folders, so the next copy fetches them again."""
    for obj, _ in damage:
        if obj.endswith("/"):
            root.delete_prefix(f"{key}/{obj}")
        else:
            root.delete([f"{key}/{obj}"])


def _existing(root: Root, key: str) -> FeatureCache | None:
    """The destination's cache under `key`, or None when there is none or its zarr.json cannot be read
    (an interrupted copy's or a damaged one: rewritten by this copy). Another cache stored under this key's
    name (`MisplacedCache`), or a key folder that is or holds a link, is refused, never overwritten."""
    try:
        return FeatureCache.in_root(root, key)
    except RefusedPlace:
        raise
    except CacheError:
        return None
