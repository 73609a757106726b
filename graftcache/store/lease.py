"""A writer lease on one cache key in an object store, which has no locks: generations created with
put-if-absent.

`<key>.lease/<generation>` objects hold {owner, expires}. A writer takes generation g+1 with a
put-if-absent when generation g is released or expired; of two writers racing for the same generation
exactly one create succeeds, the other waits. The holder renews its own generation on a heartbeat thread,
so a writer killed with SIGKILL stops renewing and its lease expires after LEASE_S seconds. Before it
publishes `complete`, a holder checks that nobody took a later generation (it was not presumed dead).
"""

from __future__ import annotations

import json
import os
import socket
import threading
import time
import uuid
from collections.abc import Callable, Mapping
from typing import Protocol

from graftcache.errors import CacheError

LEASE_ENV = "GRAFTCACHE_LEASE_S"
LEASE_S = 30.0  # expiry of an unrenewed lease; renewed every third of it


class LeaseStore(Protocol):
    """What a lease needs of its root (an object-store root implements it): a name, listing, reads and
    put-if-absent writes."""

    @property
    def url(self) -> str: ...
    def sizes(self, prefix: str) -> Mapping[str, int]: ...
    def get(self, rel: str) -> bytes | None: ...
    def put(self, rel: str, data: bytes, *, if_absent: bool = False) -> bool: ...


def lease_seconds() -> float:
    return float(os.environ.get(LEASE_ENV, LEASE_S))


class Lease:
    def __init__(self, root: LeaseStore, key: str, on_wait: Callable[[str], None] | None = None) -> None:
        self.root, self.key, self.on_wait = root, key, on_wait
        self.owner = f"{socket.gethostname()}:{os.getpid()}:{uuid.uuid4().hex[:8]}"
        self.generation = -1
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def _rel(self, generation: int) -> str:
        return f"{self.key}.lease/{generation:08d}"

    def _latest(self) -> tuple[int, dict | None]:
        gens = sorted(int(rel.rsplit("/", 1)[1]) for rel in self.root.sizes(f"{self.key}.lease/"))
        if not gens:
            return -1, None
        raw = self.root.get(self._rel(gens[-1]))
        return gens[-1], (json.loads(raw) if raw else None)

    def _record(self, *, released: bool = False) -> bytes:
        return json.dumps({"owner": self.owner, "expires": time.time() + lease_seconds(),
                           "released": released}).encode()

    def __enter__(self) -> Lease:
        told = False
        while True:
            gen, record = self._latest()
            free = record is None or record.get("released") or record["expires"] < time.time()
            if free and self.root.put(self._rel(gen + 1), self._record(), if_absent=True):
                self.generation = gen + 1
                break
            if not free and not told and self.on_wait is not None:
                self.on_wait(record["owner"])
                told = True
            time.sleep(min(1.0, lease_seconds() / 10))
        self._thread = threading.Thread(target=self._renew, daemon=True)
        self._thread.start()
        return self

    def _renew(self) -> None:
        while not self._stop.wait(lease_seconds() / 3):
            self.root.put(self._rel(self.generation), self._record())

    def check(self) -> None:
        """Raise unless this process still holds the newest generation."""
        gen, _ = self._latest()
        if gen != self.generation:
            raise CacheError(f"{self.root.url}/{self.key}: another writer took over this key (lease generation "
                             f"{gen}, ours {self.generation}); its result will be the cache")

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        self.root.put(self._rel(self.generation), self._record(released=True))
