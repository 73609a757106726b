"""A dataset's identity: size + sha256 of every file its numbers come from, remembered between runs.

The identity covers the metadata files *and* every data parquet and mp4 the episodes use, so an edited
parquet, a re-encoded video or a re-rendered episode under unchanged `meta/` files is a different
dataset (and a different cache key). File modification times are not part of it: touching a file
changes nothing.

Hashing hundreds of GB on every run would be prohibitive, so each file's hash is remembered in a small
sidecar keyed by the file's resolved path, size, mtime_ns, ctime_ns and inode. A file rewritten in place
or replaced is hashed again even if its mtime was put back (the kernel sets ctime on every write and
metadata change, and no one can set it back); touching a file costs a re-hash of that file, never a
different identity. The sidecar lives under the graftcache home (`$GRAFTCACHE_HOME/file-hashes`, or the
per-user `$XDG_CACHE_HOME/graftcache/file-hashes` when that is unset or not writable), never next to the
dataset, which may be read-only; when it cannot be read or written the hashes are simply recomputed.

Two stand-ins avoid hashing on the first run where the Hugging Face hub already recorded the hash:
a file of a hub-cache snapshot that links to `blobs/<sha256>` (the LFS object id is the sha256 of the
content), and a file of a `local_dir` download (lerobot's own `$HF_LEROBOT_HOME/<repo>`) whose
`.cache/huggingface/download/<file>.metadata` records a sha256 etag and was written after the file's
last modification (huggingface_hub's own freshness rule). Both give the same value as hashing, so a
hub snapshot and a plain copy of it have the same identity.

Comparing a recorded identity with the current one (which file differs first) is
`graftcache.store.key.compare_identity`.

    identity = {"codebase_version": "v3.0",            # added by the manifest builder
                "files": {"meta/info.json": {"size": 3233, "sha256": "..."}, "data/...": {...}, ...}}
"""

from __future__ import annotations

import json
import os
import re
import threading
from collections.abc import Iterable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from graftcache.errors import DatasetError
from graftcache.hashing import sha256_bytes, sha256_file

#: Environment variable naming the folder of hash sidecars (default: see `memo_dirs`).
MEMO_ENV = "GRAFTCACHE_HASH_MEMO"
MEMO_DIR = "file-hashes"
_SHA256 = re.compile(r"^[0-9a-f]{64}$")
#: Thread count for hashing (hashlib releases the GIL on large updates, so threads use several cores/disks).
HASH_THREADS = max(1, min(8, os.cpu_count() or 1))


def memo_dirs() -> list[Path]:
    """Where hash sidecars are read and written, in order: `$GRAFTCACHE_HASH_MEMO` alone when set; else
    `$GRAFTCACHE_HOME/file-hashes`, then the per-user `$XDG_CACHE_HOME/graftcache/file-hashes`
    (default `~/.cache/...`), which takes over when a shared home is not writable by this user."""
    if os.environ.get(MEMO_ENV):
        return [Path(os.environ[MEMO_ENV]).expanduser()]
    xdg = os.environ.get("XDG_CACHE_HOME")
    user = (Path(xdg).expanduser() if xdg else Path.home() / ".cache") / "graftcache" / MEMO_DIR
    home = os.environ.get("GRAFTCACHE_HOME")
    return list(dict.fromkeys([Path(home).expanduser() / MEMO_DIR, user] if home else [user]))


# ---------------------------------------------------------------------------------------------- computing
@dataclass
class HashStats:
    """What one `content_identity` call did (filled in for a caller that passes one: timing, tests)."""

    files: int = 0         # files in the identity
    bytes_total: int = 0   # their total size
    hashed_files: int = 0  # read and hashed by this call (new or changed since the memo)
    hashed_bytes: int = 0
    from_memo: int = 0     # taken from the hash sidecar (size, mtime, ctime and inode unchanged)
    from_hub: int = 0      # taken from the hub's own record (blob name or download metadata)


def content_identity(root: Path, files: Iterable[Path], *, progress: bool = True,
                     stats: HashStats | None = None) -> dict[str, Any]:
    """{"files": {relative path: {"size", "sha256"}}} for `files` (under `root`), in the given order; `stats`, when
    given, is filled in with what this call did (how many files were hashed, taken from the memo or the hub).

    Raises DatasetError naming the first file that is missing or unreadable.
    """
    root = Path(root)
    paths = list(dict.fromkeys(Path(p) for p in files))
    stat: dict[Path, os.stat_result] = {}
    for p in paths:
        try:
            stat[p] = p.stat()
        except FileNotFoundError:
            raise DatasetError(f"{p}: missing (every data and video file is part of the dataset identity)") from None
        except OSError as e:
            raise DatasetError(f"{p}: cannot stat ({e.strerror})") from None
    memo = _Memo(root)
    run = HashStats(files=len(paths), bytes_total=sum(s.st_size for s in stat.values()))
    digests: dict[Path, str] = {}
    todo: list[Path] = []
    for p in paths:
        real = os.path.realpath(p)
        known = _hub_sha256(root, p, real, stat[p])
        if known is not None:
            run.from_hub += 1
        else:
            known = memo.get(real, stat[p])
            if known is not None:
                run.from_memo += 1
        if known is None:
            todo.append(p)
        else:
            digests[p] = known
    if todo:
        for p, digest in zip(todo, _hash_all(todo, sum(stat[p].st_size for p in todo), progress)):
            digests[p] = digest
            memo.put(os.path.realpath(p), stat[p], digest)
        run.hashed_files = len(todo)
        run.hashed_bytes = sum(stat[p].st_size for p in todo)
        memo.save()
    if stats is not None:
        vars(stats).update(vars(run))
    return {"files": {_relative(p, root): {"size": stat[p].st_size, "sha256": digests[p]} for p in paths}}


def _relative(path: Path, root: Path) -> str:
    try:
        return path.relative_to(root).as_posix()
    except ValueError:
        return path.as_posix()


def _hash_all(paths: Sequence[Path], total: int, progress: bool) -> list[str]:
    """sha256 of each path (in order), on a few threads; a progress line when there is much to read."""
    bar = None
    if progress and total >= (1 << 30):
        from graftcache.progress import progress as make_bar

        bar = make_bar(total=total / 1e6, unit="MB", desc=f"hashing {len(paths)} dataset files (first time only)")
    lock = threading.Lock()

    def one(p: Path) -> str:
        try:
            digest = sha256_file(p)
        except OSError as e:
            raise DatasetError(f"{p}: cannot read ({e.strerror})") from None
        if bar is not None:
            with lock:
                bar.update(p.stat().st_size / 1e6)
        return digest

    try:
        if len(paths) == 1 or HASH_THREADS == 1:
            return [one(p) for p in paths]
        with ThreadPoolExecutor(max_workers=HASH_THREADS) as threads:
            return list(threads.map(one, paths))
    finally:
        if bar is not None:
            bar.close()


# ---------------------------------------------------------------------------------------------- stand-ins
def _hub_sha256(root: Path, path: Path, real: str, st: os.stat_result) -> str | None:
    """The hub's own sha256 of `path`, when the hub cache or a local_dir download recorded one."""
    parent = Path(real).parent
    name = Path(real).name
    # hub cache snapshot: snapshots/<rev>/<file> -> ../../blobs/<oid>; a 64-hex oid is the LFS sha256
    if parent.name == "blobs" and parent.parent.name.startswith("datasets--") and _SHA256.match(name):
        return name
    # local_dir download: <root>/.cache/huggingface/download/<relpath>.metadata = commit, etag, timestamp
    try:
        rel = path.relative_to(root)
    except ValueError:
        return None
    meta = root / ".cache" / "huggingface" / "download" / f"{rel.as_posix()}.metadata"
    try:
        lines = meta.read_text().splitlines()
        etag, timestamp = lines[1].strip().strip('"'), float(lines[2])
    except (OSError, IndexError, ValueError):
        return None
    if _SHA256.match(etag) and st.st_mtime - 1 <= timestamp:
        return etag
    return None


# ---------------------------------------------------------------------------------------------- sidecar
class _Memo:
    """{resolved path: [size, mtime_ns, ctime_ns, inode, sha256]} for the files of one dataset root, as JSON."""

    def __init__(self, root: Path) -> None:
        real_root = os.path.realpath(root)
        name = f"{sha256_bytes(real_root.encode())[:16]}.json"
        self.paths = [d / name for d in memo_dirs()]
        self.root = real_root
        self.entries: dict[str, list] = {}
        self.dirty = False
        for path in reversed(self.paths):  # the first location wins where both know a file
            self.entries.update(self._read(path))

    def _read(self, path: Path) -> dict[str, list]:
        try:
            data = json.loads(path.read_text())
            if data.get("root") == self.root and isinstance(data.get("files"), dict):
                return {k: v for k, v in data["files"].items() if isinstance(v, list)}
        except (OSError, ValueError, AttributeError):
            pass
        return {}

    @staticmethod
    def _key(st: os.stat_result) -> list:
        return [st.st_size, st.st_mtime_ns, st.st_ctime_ns, st.st_ino]

    def get(self, real: str, st: os.stat_result) -> str | None:
        entry = self.entries.get(real)
        if isinstance(entry, list) and len(entry) == 5 and entry[:4] == self._key(st) and _SHA256.match(str(entry[4])):
            return entry[4]
        return None

    def put(self, real: str, st: os.stat_result, digest: str) -> None:
        self.entries[real] = [*self._key(st), digest]
        self.dirty = True

    def save(self) -> None:
        """Merge with what another process may have written meanwhile, then replace atomically, in the
        first location that can be written; when none can, the hashes are recomputed next time."""
        if not self.dirty:
            return
        for path in self.paths:
            tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
            try:
                path.parent.mkdir(parents=True, exist_ok=True)
                tmp.write_text(json.dumps({"root": self.root, "files": {**self._read(path), **self.entries}}))
                os.replace(tmp, path)
                self.dirty = False
                return
            except OSError:  # read-only, foreign or full: try the next location
                try:
                    tmp.unlink(missing_ok=True)
                except OSError:
                    pass
