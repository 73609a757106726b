"""Object-store failures as one line: obstore's exception types, and the S3 error codes its messages carry, are
mapped here and nowhere else, to a StoreError naming the root URL (or bucket) and the object.

Every obstore call of graftcache runs inside `mapped(where)`: ObjectRoot's whole-object calls
(graftcache.store.roots) and Zarr's reads and writes of a cache (`NamedObjectStore`). A missing object stays a
missing object (None, "no feature cache here"); a missing bucket, refused credentials or an endpoint that does not
answer become StoreError. How long an unanswered request is retried is $GRAFTCACHE_STORE_RETRY_S
(graftcache.store.roots.retry_config): obstore's own default budget otherwise.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

from zarr.storage import ObjectStore

from graftcache.errors import CacheError

#: The environment each scheme takes its credentials from, named when a store refuses them.
CREDENTIALS = {"s3": "AWS_ACCESS_KEY_ID / AWS_SECRET_ACCESS_KEY / AWS_PROFILE",
               "gs": "GOOGLE_SERVICE_ACCOUNT / GOOGLE_APPLICATION_CREDENTIALS",
               "az": "AZURE_STORAGE_ACCOUNT_NAME / AZURE_STORAGE_ACCOUNT_KEY / AZURE_STORAGE_SAS_KEY"}
_REQUEST = re.compile(r"(?:GET|PUT|HEAD|POST|DELETE) (\w+://[^/\s?]+)")
_RETRIES = re.compile(r" in ([\d.]+)(ns|µs|ms|s), after (\d+) retries")
_UNIT_S = {"ns": 1e-9, "µs": 1e-6, "ms": 1e-3, "s": 1.0}


class StoreError(CacheError):
    """An object store refused a request or did not answer it."""


@dataclass(frozen=True)
class Failure:
    """One kind of store failure: how it shows in obstore's exception, and the line that replaces it."""

    matches: Callable[[BaseException, str], bool]
    line: Callable[[str, str], str]  # (where, obstore's message) -> the one line


def _text_has(*codes: str) -> Callable[[BaseException, str], bool]:
    return lambda e, text: any(code in text for code in codes)


def _type_is(*names: str) -> Callable[[BaseException, str], bool]:
    return lambda e, text: type(e).__name__ in names


def _bucket(where: str) -> str:
    scheme, _, rest = where.partition("://")
    return f"{scheme}://{rest.split('/')[0]}"


def _endpoint(text: str) -> str:
    found = _REQUEST.search(text)
    return found.group(1) if found else "the store"


def _unreachable(where: str, text: str) -> str:
    tries = _RETRIES.search(text)
    spent = (f" after {tries.group(3)} retries in {float(tries.group(1)) * _UNIT_S[tries.group(2)]:.1f} s"
             if tries else "")
    return (f"{where}: {_endpoint(text)} did not answer{spent} (endpoint down or unreachable); what was copied "
            f"or written before stays: run the same command again to resume")


def _denied(where: str, text: str) -> str:
    names = CREDENTIALS.get(where.partition("://")[0], "the store's credentials")
    return f"{where}: access denied by {_endpoint(text)}; check the credentials ({names})"


#: First match wins: the S3 code of a missing bucket also arrives inside a "not found".
FAILURES: tuple[Failure, ...] = (
    Failure(_text_has("NoSuchBucket"), lambda where, text: f"{_bucket(where)}: the bucket does not exist "
                                                             f"(at {_endpoint(text)}; needed for {where})"),
    Failure(lambda e, text: _type_is("PermissionDeniedError", "UnauthenticatedError")(e, text) or _text_has(
        "InvalidAccessKeyId", "SignatureDoesNotMatch", "AccessDenied", "403 Forbidden", "401 Unauthorized",
        "ExpiredToken", "InvalidToken")(e, text), _denied),
    Failure(_text_has("error sending request", "HTTP error", "timed out", "operation timed out", "Connection reset",
                      "connection closed"), _unreachable),
)


def _from_obstore(e: BaseException) -> bool:
    from obstore.exceptions import BaseError

    return isinstance(e, BaseError) or (isinstance(e, FileNotFoundError) and "NoSuchBucket" in str(e))


def store_error(e: BaseException, where: str) -> StoreError | None:
    """The one-line StoreError for an obstore failure at `where` (a URL); None for any other exception, and for
    a plain missing object (callers treat absence themselves)."""
    if not _from_obstore(e):
        return None
    text = str(e)
    for failure in FAILURES:
        if failure.matches(e, text):
            return StoreError(failure.line(where, text))
    first = " ".join(text.split("Debug source:")[0].split())
    return StoreError(f"{where}: {type(e).__name__}: {first[:300]}")


def absent(e: BaseException) -> bool:
    """An object that is not there (as opposed to a bucket that is not there)."""
    from obstore.exceptions import NotFoundError

    return isinstance(e, (NotFoundError, FileNotFoundError)) and "NoSuchBucket" not in str(e)


@contextmanager
def mapped(where: str) -> Iterator[None]:
    """Obstore failures inside the block leave it as StoreError naming `where`."""
    try:
        yield
    except Exception as e:
        error = store_error(e, where)
        if error is None:
            raise
        raise error from None


class NamedObjectStore(ObjectStore):
    """Zarr's ObjectStore for one cache, whose failures name the cache's URL and the object (`mapped`)."""

    def __init__(self, store: Any, *, read_only: bool = False, url: str = "") -> None:
        super().__init__(store, read_only=read_only)
        self.url = url

    def with_read_only(self, read_only: bool = False) -> NamedObjectStore:
        return type(self)(self.store, read_only=read_only, url=self.url)

    async def get(self, key: str, *args: Any, **kwargs: Any) -> Any:
        with mapped(f"{self.url}/{key}"):
            return await super().get(key, *args, **kwargs)

    async def get_partial_values(self, prototype: Any, key_ranges: Any) -> Any:
        key_ranges = list(key_ranges)
        with mapped(f"{self.url}/{key_ranges[0][0] if key_ranges else ''}"):
            return await super().get_partial_values(prototype, key_ranges)

    async def exists(self, key: str) -> bool:
        with mapped(f"{self.url}/{key}"):
            return await super().exists(key)

    async def set(self, key: str, value: Any) -> None:
        with mapped(f"{self.url}/{key}"):
            await super().set(key, value)

    async def set_if_not_exists(self, key: str, value: Any) -> None:
        with mapped(f"{self.url}/{key}"):
            await super().set_if_not_exists(key, value)

    async def delete(self, key: str) -> None:
        with mapped(f"{self.url}/{key}"):
            await super().delete(key)

    async def getsize(self, key: str) -> int:
        with mapped(f"{self.url}/{key}"):
            return await super().getsize(key)
