"""Cache roots: a local folder or an object-store URL, behind one small interface.

A root holds one Zarr v3 group per cache key (`<root>/<key>/...`). Everything the cache format needs
beyond Zarr itself is four operations on whole objects (get, put, put-if-absent, list/delete a prefix),
so the same layout, manifest, checksums and complete-last protocol serve every store.

Object stores go through obstore (`zarr.storage.ObjectStore`), not fsspec + s3fs, because:
- obstore is one self-contained wheel; s3fs pulls aiobotocore, which pins botocore to a narrow range that
  conflicts with boto3 (moto's) and breaks `pip check` in scripts/setup.sh;
- it has put-if-absent (`mode="create"`, S3 If-None-Match) as a first-class call, which the writer lease
  and publishing need on stores without locks;
- s3://, gs://, az:// (and http(s)://) URLs, credentials and endpoints come from each store's standard
  environment (AWS_*, incl. AWS_ENDPOINT_URL; GOOGLE_*; AZURE_*). hf:// is not an object_store scheme.
Local folders keep zarr's LocalStore (temp file + rename per object) and plain files.

Nothing outside a root is reached through it: every key and object path is checked against the key grammar
(graftcache.store.key) before any I/O, and a local root refuses, never follows, a symbolic link on the way to
an object (a key folder that is a link, a link inside a cache), so reading, replacing or deleting a cache
never touches the files a link points to.
"""

from __future__ import annotations

import os
import shutil
import stat
import uuid
from abc import ABC, abstractmethod
from collections.abc import Callable
from contextlib import AbstractContextManager
from pathlib import Path
from typing import Any

from zarr.abc.store import Store

from graftcache.errors import CacheError
from graftcache.store.key import RefusedPlace, check_key, check_writer
from graftcache.store.remote_errors import NamedObjectStore, absent, mapped

GROUP_META = "zarr.json"
ENV_HOME = "GRAFTCACHE_HOME"
LEASE_SUFFIX = ".lease"  # `<writer>.lease/<generation>`: an object store's writer lease (store/lease.py)
#: Seconds an object-store request that gets no answer is retried before the command fails (obstore's default,
#: 180, when unset); what was copied or written before stays, and the same command resumes.
ENV_RETRY_S = "GRAFTCACHE_STORE_RETRY_S"


def is_url(spec: str | Path) -> bool:
    return "://" in str(spec)


def default_home() -> Path:
    return Path.home() / ".cache" / "graftcache"


class Root(ABC):
    """Where caches live. `rel` paths are `<key>/<path inside the cache>`, '/'-separated."""

    @property
    @abstractmethod
    def url(self) -> str:
        """How the user names this root (a path or a URL)."""

    def __str__(self) -> str:
        return self.url

    def location(self, key: str) -> str | Path:
        return f"{self.url.rstrip('/')}/{check_key(key)}"

    @abstractmethod
    def zarr_store(self, key: str, *, read_only: bool) -> Store:
        """The Zarr store of one cache."""

    @abstractmethod
    def get(self, rel: str) -> bytes | None:
        """The object's bytes, or None when absent."""

    @abstractmethod
    def put(self, rel: str, data: bytes, *, if_absent: bool = False) -> bool:
        """Write one object whole (readers see the old or the new bytes, never a part). With `if_absent`,
        False (and nothing written) when the object already exists."""

    @abstractmethod
    def sizes(self, prefix: str) -> dict[str, int]:
        """Every object under `prefix` ('<key>/' or '<key>.lease/'), as rel path -> bytes."""

    @abstractmethod
    def delete(self, rels: list[str]) -> None:
        """Remove these objects (absent ones are no error)."""

    @abstractmethod
    def keys(self) -> list[str]:
        """Names of the top-level folders that hold a group's zarr.json, sorted."""

    @abstractmethod
    def writer(self, key: str, on_wait: Callable[[str], None] | None = None) -> AbstractContextManager[Any]:
        """Held while one process writes `key`: a second writer waits, then finds the key complete."""

    def delete_prefix(self, prefix: str) -> None:
        self.delete(list(self.sizes(prefix)))

    def fetch(self, key: str, rels: list[str]) -> None:  # noqa: B027 (a no-op by default, not abstract)
        """Make these objects of cache `key` local before Zarr reads them; only a read-through root has work."""


class LocalRoot(Root):
    def __init__(self, path: Path) -> None:
        self.path = path

    @property
    def url(self) -> str:
        return str(self.path)

    def location(self, key: str) -> Path:
        return self.path / check_key(key)

    def _path(self, rel: str) -> Path:
        """The file or folder of `rel` (checked by `object_parts`), refused when it or a folder on the way to
        it from the root is a symbolic link, or a folder on the way is a file."""
        parts = object_parts(rel)
        path = self.path
        for depth, part in enumerate(parts, 1):
            path = path / part
            try:
                mode = path.lstat().st_mode
            except FileNotFoundError:
                break  # nothing below it exists either
            if stat.S_ISLNK(mode):
                raise RefusedPlace(_link(path))
            if depth < len(parts) and not stat.S_ISDIR(mode):
                raise RefusedPlace(f"{path} is a file where a folder of a cache belongs; graftcache neither reads "
                                   "nor replaces it")
        return self.path.joinpath(*parts)

    def _walk(self, folder: Path) -> list[Path]:
        """Every file under `folder`, refusing any symbolic link in it (os.walk itself never follows one)."""
        files = []
        for at, dirs, names in os.walk(folder):
            for name in dirs + names:
                if os.path.islink(os.path.join(at, name)):
                    raise RefusedPlace(_link(Path(at, name)))
            files += [Path(at, name) for name in names]
        return files

    def zarr_store(self, key: str, *, read_only: bool) -> Store:
        from zarr.storage import LocalStore

        folder = self._path(check_key(key))
        self._walk(folder)  # zarr follows links: a cache holding one is refused before zarr reads through it
        return LocalStore(folder, read_only=read_only)

    def get(self, rel: str) -> bytes | None:
        try:
            return self._path(rel).read_bytes()
        except FileNotFoundError:
            return None

    def get_size(self, rel: str) -> int | None:
        try:
            return self._path(rel).stat().st_size
        except FileNotFoundError:
            return None

    def put(self, rel: str, data: bytes, *, if_absent: bool = False) -> bool:
        target = self._path(rel)
        target.parent.mkdir(parents=True, exist_ok=True)
        tmp = target.parent / f".{target.name}.{os.getpid()}.{uuid.uuid4().hex[:8]}"
        try:
            tmp.write_bytes(data)  # an ordinary create: the mode follows the umask, as zarr's own files do
            if not if_absent:
                os.replace(tmp, target)
                return True
            try:
                os.link(tmp, target)  # atomic put-if-absent on POSIX file systems
            except FileExistsError:
                return False
            return True
        finally:
            tmp.unlink(missing_ok=True)

    def sizes(self, prefix: str) -> dict[str, int]:
        base = self._path(prefix)
        if not base.is_dir():
            return {}
        return {p.relative_to(self.path).as_posix(): p.stat().st_size for p in self._walk(base)
                if not p.name.startswith(".")}

    def delete(self, rels: list[str]) -> None:
        for rel in rels:
            self._path(rel).unlink(missing_ok=True)

    def delete_prefix(self, prefix: str) -> None:
        folder = self._path(prefix)
        if folder.is_dir():
            self._walk(folder)  # a link inside is refused, so what is deleted is exactly what the root holds
            shutil.rmtree(folder, ignore_errors=True)

    def keys(self) -> list[str]:
        """Folders holding a zarr.json, by name: a badly named one or a link is listed here and refused by
        name when opened (`graftcache ls` shows it as broken)."""
        if not self.path.is_dir():
            return []
        return sorted(p.name for p in self.path.iterdir() if (p / GROUP_META).exists())

    def writer(self, key: str, on_wait: Callable[[str], None] | None = None) -> AbstractContextManager[Any]:
        from graftcache.store.lock import exclusive

        return exclusive(self.path / f"{check_writer(key)}.lock", on_wait=on_wait)


class ObjectRoot(Root):
    """s3://bucket/prefix, gs://..., az://...: one obstore store for the root, one per cache for Zarr."""

    def __init__(self, url: str) -> None:
        self._url = url.rstrip("/")
        self.store = _obstore(self._url)

    @property
    def url(self) -> str:
        return self._url

    def zarr_store(self, key: str, *, read_only: bool) -> Store:
        url = f"{self._url}/{check_key(key)}"
        return NamedObjectStore(_obstore(url), read_only=read_only, url=url)

    def _at(self, rel: str) -> str:
        return f"{self._url}/{rel}"

    def get(self, rel: str) -> bytes | None:
        import obstore

        with mapped(self._at(rel)):
            try:
                return bytes(obstore.get(self.store, "/".join(object_parts(rel))).bytes())
            except Exception as e:
                if absent(e):
                    return None
                raise

    def put(self, rel: str, data: bytes, *, if_absent: bool = False) -> bool:
        import obstore
        from obstore.exceptions import AlreadyExistsError, PreconditionError

        with mapped(self._at(rel)):
            try:
                obstore.put(self.store, "/".join(object_parts(rel)), data,
                            mode="create" if if_absent else "overwrite")
            except (AlreadyExistsError, PreconditionError):
                return False
        return True

    def sizes(self, prefix: str) -> dict[str, int]:
        import obstore

        object_parts(prefix)
        with mapped(self._at(prefix)):
            return {m["path"]: int(m["size"]) for batch in obstore.list(self.store, prefix) for m in batch
                    if m["path"].startswith(prefix)}

    def delete(self, rels: list[str]) -> None:
        import obstore

        for rel in rels:
            object_parts(rel)
        for start in range(0, len(rels), 1000):
            with mapped(self._at(rels[start])):
                obstore.delete(self.store, rels[start:start + 1000])

    def keys(self) -> list[str]:
        """Listed folders holding a zarr.json, by name, as the store lists them (so one named outside the key
        grammar is listed, and refused by name when opened)."""
        import obstore

        def holds_group(prefix: str) -> bool:
            with mapped(self._at(f"{prefix}{GROUP_META}")):
                try:
                    obstore.head(self.store, f"{prefix}{GROUP_META}")
                except Exception as e:
                    if absent(e):
                        return False
                    raise
            return True

        with mapped(self._url):
            listed = obstore.list_with_delimiter(self.store)
        return sorted(p.rstrip("/") for p in listed["common_prefixes"] if holds_group(p.rstrip("/") + "/"))

    def writer(self, key: str, on_wait: Callable[[str], None] | None = None) -> AbstractContextManager[Any]:
        from graftcache.store.lease import Lease

        return Lease(self, check_writer(key), on_wait=on_wait)


def object_parts(rel: str) -> list[str]:
    """The '/'-separated parts of an object path inside a root (`<key>/...`, `<writer>.lease/...`; a prefix
    may end in '/'), or a one-line CacheError: the first part names a key, no part is empty, '.' or '..'."""
    parts = rel.removesuffix("/").split("/")
    check_writer(parts[0].removesuffix(LEASE_SUFFIX))
    if any(part in ("", ".", "..") for part in parts[1:]):
        raise RefusedPlace(f"{rel!r}: not an object inside a cache (an empty, '.' or '..' part)")
    return parts


def _link(path: Path) -> str:
    return (f"{path} is a symbolic link; a cache root holds no links (a key is its own folder), so "
            "graftcache does not follow it, and reads, writes and deletes nothing through it")


def _obstore(url: str):
    """An obstore store for `url`, configured from the environment; http:// endpoints (S3-compatible
    servers on a LAN or loopback) are allowed when AWS_ENDPOINT_URL names one."""
    from obstore.store import from_url

    options: dict[str, Any] = {"retry_config": retry_config()}
    if os.environ.get("AWS_ENDPOINT_URL", "").startswith("http://"):
        options["client_options"] = {"allow_http": True}
    try:
        return from_url(url, **options)
    except Exception as e:  # unknown scheme, bad bucket name, missing configuration
        raise CacheError(f"{url}: cannot open this cache root ({type(e).__name__}: {e})") from None


def retry_config() -> dict[str, Any]:
    """obstore's retry settings: its defaults, with the total time bounded by $GRAFTCACHE_STORE_RETRY_S."""
    from datetime import timedelta

    seconds = os.environ.get(ENV_RETRY_S)
    if not seconds:
        return {}
    try:
        value = float(seconds)
    except ValueError:
        raise CacheError(f"${ENV_RETRY_S}={seconds!r} is not a number of seconds") from None
    return {"retry_timeout": timedelta(seconds=value),
            "backoff": {"init_backoff": timedelta(seconds=min(0.1, value / 10)),
                        "max_backoff": timedelta(seconds=max(value / 4, 0.01))}}


def cache_root(explicit: str | Path | None = None) -> Path:
    """The local folder for things that are never shared through a remote root (tiny policies, demo
    results, the read-through cache): `--cache DIR` when it is a folder, else $GRAFTCACHE_HOME when it
    is a folder, else ~/.cache/graftcache."""
    for spec in (explicit, os.environ.get(ENV_HOME)):
        if spec and not is_url(spec):
            return _folder(spec)
    return _folder(default_home())


def open_root(explicit: str | Path | Root | None = None) -> Root:
    """`--cache DIR|URL`, else $GRAFTCACHE_HOME, else ~/.cache/graftcache."""
    if isinstance(explicit, Root):
        return explicit
    spec = explicit or os.environ.get(ENV_HOME) or default_home()
    return ObjectRoot(str(spec)) if is_url(spec) else LocalRoot(_folder(spec))


def _folder(spec: str | Path) -> Path:
    """A local root's folder (made when first written); one that exists as a file is refused by name."""
    path = Path(spec).expanduser()
    if path.exists() and not path.is_dir():
        raise CacheError(f"cache root {path} is a file, not a folder: --cache (or ${ENV_HOME}) names a "
                         "folder (made when absent) or an s3:// gs:// az:// URL")
    return path


def split_location(location: str | Path) -> tuple[Root, str]:
    """A cache's location (a folder or a URL) as (root, key)."""
    text = str(location).rstrip("/")
    if is_url(text):
        parent, _, key = text.rpartition("/")
        return ObjectRoot(parent), key
    path = Path(text)
    return LocalRoot(path.parent), path.name

