"""FeatureCache: one Zarr v3 group per key, written block by block, resumable, checksummed.

Layout choices (why):
- Feature arrays are [frames, tokens, C]. The unit of work is a *block* of `block_frames`
  consecutive frames, and each block is exactly one *block file* per array (what zarr's sharding codec
  writes; `shards=` below). A block is written in a single call, so zarr writes each block file once
  (atomically: LocalStore writes a temp file and renames it), and a run killed mid-block leaves no
  half-written block file that looks finished.
- Inside a block file, inner zarr chunks hold ~4 MiB of uncompressed features, so random access to a few
  frames (stage 2 batches, `verify`) decompresses little, while a block of 256 frames keeps the
  file count of a 273k-frame LIBERO cache in the low thousands.
- Blosc-zstd with byte shuffle on 2-byte floats: fast to decode, and shuffling the high bytes
  together is what lets fp16 activations compress at all.
- A block is "done" only when a marker holding the sha256 of every array's block bytes has been
  written (atomically) after the data. `complete` is set in the group attributes only after every
  block has a marker; the checksums then move into the attributes and `verify` re-reads them.
  The attributes live in the group's zarr.json, one object written whole, so publishing `complete` is a
  single atomic put on a local disk and on an object store alike (graftcache.store.roots).
- Stage 2 checks every block it reads against its checksum, once per block per reader (`BlockChecks`, owned by
  the handle, shared by a fit's handles and handed to its worker processes, graftcache.fit.stream), reading whole
  blocks for that: a corrupt block file is a one-line CacheError naming cache, array and block.
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from datetime import UTC, datetime
from functools import cached_property
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import polars as pl
import zarr
from zarr.codecs import BloscCodec

from graftcache.errors import CacheError
from graftcache.hashing import sha256_bytes
from graftcache.store.key import (
    IdentityDifference,
    RefusedPlace,
    cache_key,
    check_key,
    compare_identity,
    identity_of,
)
from graftcache.store.manifest import Manifest, stored_key
from graftcache.store.roots import GROUP_META, Root, open_root, split_location

if TYPE_CHECKING:  # torch is imported where features are converted: listing caches (graftcache ls) needs none
    import torch

ZARR_CHUNK_BYTES = 4 << 20
ACTION_STREAM = "action_stream"  # group of the full-rate actions (see FeatureCache.create)
STORAGE_DTYPES: dict[str, np.dtype] = {
    "fp16": np.dtype(np.float16),
    "fp32": np.dtype(np.float32),
    "bf16": np.dtype(np.uint16),  # numpy has no bfloat16: raw bits, tagged in the array attributes
}
PROGRESS_DIR = "_progress"
#: zarr's LocalStore writes `<object>.<uuid>.partial` and renames it; a writer killed mid-write leaves one behind.
PARTIAL_SUFFIX = ".partial"


class BlockChecks:
    """The blocks read back against their checksums: (cache location, array, block), block -1 for a static array.

    Owned by whoever reads (a cache handle, or every handle of one fit: graftcache.fit.stream.CacheReader) and
    pickled with it into the worker processes it starts, so a block is checked once per reader whichever process
    reads it, also in workers that inherit nothing (a fork server's). `count` is the checks made for this reader:
    here, plus those its workers reported (`update`)."""

    def __init__(self) -> None:
        self.done: set[tuple[str, str, int]] = set()
        self.count = 0

    def __contains__(self, block: tuple[str, str, int]) -> bool:
        return block in self.done

    def add(self, block: tuple[str, str, int]) -> None:
        """A block this process checked."""
        self.done.add(block)
        self.count += 1

    def update(self, blocks: Iterable[tuple[str, str, int]]) -> None:
        """Blocks a worker process checked for this reader: counted, and never checked again."""
        for block in blocks:
            self.add(block)


def _compressor(itemsize: int) -> BloscCodec:
    """Blosc zstd level 1 with byte shuffle: on fp16 features it compresses as well as level 3 at a fraction of
    its cost, and far better than lz4 (docs/measured.md). Compression runs beside the encoder on the same cores,
    so a slower level costs extraction throughput for no smaller files."""
    return BloscCodec(cname="zstd", clevel=1, shuffle="shuffle", typesize=itemsize)


def _sha256(a: np.ndarray) -> str:
    return sha256_bytes(np.ascontiguousarray(a).tobytes())


def to_storage(t: torch.Tensor, dtype: str) -> np.ndarray:
    """Convert computed features to the stored numpy representation of `dtype`."""
    import torch

    if dtype == "bf16":
        return t.detach().to("cpu", torch.bfloat16).view(torch.uint16).numpy()
    return t.detach().to("cpu", torch.float16 if dtype == "fp16" else torch.float32).numpy()


def from_storage(a: np.ndarray, dtype: str) -> torch.Tensor:
    """Inverse of `to_storage`: a torch tensor in the stored precision."""
    import torch

    t = torch.from_numpy(np.ascontiguousarray(a))
    return t.view(torch.bfloat16) if dtype == "bf16" else t


class MisplacedCache(RefusedPlace):
    """A folder holds a cache whose manifest hashes to another key than the folder's name (copied or renamed
    by hand): it is not the cache of that name, and nothing may use, replace or delete it as such."""

    def __init__(self, location: str | Path, folder_key: str, own_key: str) -> None:
        super().__init__(f"{location}: not cache {folder_key}: its manifest hashes to {own_key} (a cache's "
                         f"folder is named by its key; copied or renamed by hand?); rename the folder to "
                         f"{own_key} to use it; nothing was changed")
        self.folder_key, self.own_key = folder_key, own_key


@dataclass(frozen=True)
class ArraySpec:
    """One feature array: its path in the group and the shape of one frame's entry."""

    path: str  # e.g. "features/image/8x8"
    frame_shape: tuple[int, ...]  # (tokens, C)


class FeatureCache:
    """One cache: `FeatureCache(path or URL)`, or `FeatureCache.in_root(root, key)`; make new ones with `create`.

    `writable=False` opens the group read-only (ls, info, verify, fit): nothing is ever written. A folder
    whose manifest hashes to another key than its name is refused (`MisplacedCache`)."""

    @classmethod
    def in_root(cls, root: Root, key: str, *, writable: bool = False,
                checks: BlockChecks | None = None) -> FeatureCache:
        """The cache `key` of an opened root (its objects read and written through that root)."""
        return cls(root.location(key), root=root, key=key, writable=writable, checks=checks)

    def __init__(self, location: str | Path, *, root: Root | None = None, key: str | None = None,
                 writable: bool = True, checks: BlockChecks | None = None) -> None:
        """`checks`: the blocks already checked by the reader this handle belongs to (default: its own)."""
        if root is None or key is None:
            root, key = split_location(location)
        check_key(key)
        self.path, self.root, self._key, self._writable = location, root, key, writable
        self.checks = BlockChecks() if checks is None else checks
        raw = root.get(f"{key}/{GROUP_META}")
        if raw is None:
            raise CacheError(f"{location}: no feature cache here (zarr.json missing)")
        try:
            self._opened_attrs = json.loads(raw)["attributes"]
            stored = dict(self._opened_attrs["manifest"])
        except (ValueError, KeyError, TypeError) as e:
            raise CacheError(f"{location}: zarr.json is not a feature cache's ({type(e).__name__}: {e})") from None
        try:
            own = stored_key(stored)  # what is stored, in its own format, names the folder
        except (KeyError, TypeError):
            own = key  # identity fields absent: a format older than any Manifest.read upgrades, refused there
        if own != key:
            raise MisplacedCache(location, key, own)
        self.manifest = Manifest.read(stored, str(location), key)  # refuses what it cannot read, in one line

    @cached_property
    def group(self) -> zarr.Group:
        """The Zarr group, opened on first use: listing caches and reading manifests (ls, choosing a cache
        for a fit) needs only the zarr.json read above, so a remote root's other objects are not touched."""
        return zarr.open_group(store=self.root.zarr_store(self.key, read_only=not self._writable),
                               mode="r+" if self._writable else "r", zarr_format=3)

    # ------------------------------------------------------------------ creation
    @classmethod
    def create(
        cls,
        path: str | Path,
        manifest: Manifest,
        arrays: Iterable[ArraySpec],
        index: pl.DataFrame,
        *,
        block_frames: int,
        action_stream: pl.DataFrame | None = None,
        root: Root | None = None,
    ) -> FeatureCache:
        """Create the group, its arrays, and write the index and low-dim columns.

        `index` has one row per cached frame in cache order with columns index, episode_index,
        frame_index, task_index, suite_index, timestamp, state (array), action (array).
        `action_stream` (columns episode_index, frame_index, action) is every frame of the cached episodes
        at the dataset's full rate (default: `index` itself): with a frame stride only every k-th frame has
        features, but an action chunk is the next actions at full rate (stored as ACTION_STREAM/*).
        Anything already at `path` (an interrupted initialisation) is removed first. `path` ends in the
        manifest's own key (a cache is only ever made under its key).
        """
        parent, key = split_location(path)
        root = root or parent
        own = cache_key(manifest.to_dict())
        if key != own:
            raise CacheError(f"{path}: a cache is made under its own key, {own}, not under {key!r}")
        root.delete_prefix(f"{key}/")
        n = index.height
        dtype = manifest.storage_dtype
        np_dtype = STORAGE_DTYPES[dtype]
        group = zarr.open_group(store=root.zarr_store(key, read_only=False), mode="w", zarr_format=3)
        group.attrs.update({"manifest": manifest.to_dict(), "initialized": False, "complete": False})
        arrays = list(arrays)
        for spec in arrays:
            frame_bytes = int(np.prod(spec.frame_shape)) * np_dtype.itemsize
            inner = max(1, min(block_frames, ZARR_CHUNK_BYTES // max(frame_bytes, 1)))
            while block_frames % inner:
                inner -= 1
            group.create_array(
                spec.path,
                shape=(n, *spec.frame_shape),
                dtype=np_dtype,
                chunks=(inner, *spec.frame_shape),
                shards=(block_frames, *spec.frame_shape),
                compressors=_compressor(np_dtype.itemsize),
                fill_value=0,
                attributes={"graftcache_dtype": dtype},
            )
        static_sums = {}
        for name in ("index", "episode_index", "frame_index", "task_index", "suite_index"):
            static_sums[f"index/{name}"] = cls._write_static(group, f"index/{name}", index[name].to_numpy())
        static_sums["lowdim/timestamp"] = cls._write_static(
            group, "lowdim/timestamp", index["timestamp"].to_numpy().astype(np.float32)
        )
        for name in ("state", "action"):
            values = np.asarray(index[name].to_list(), dtype=np.float32).reshape(n, -1)
            static_sums[f"lowdim/{name}"] = cls._write_static(group, f"lowdim/{name}", values)
        stream = index if action_stream is None else action_stream
        for name in ("episode_index", "frame_index"):
            static_sums[f"{ACTION_STREAM}/{name}"] = cls._write_static(group, f"{ACTION_STREAM}/{name}",
                                                                      stream[name].to_numpy())
        static_sums[f"{ACTION_STREAM}/action"] = cls._write_static(
            group, f"{ACTION_STREAM}/action",
            np.asarray(stream["action"].to_list(), dtype=np.float32).reshape(stream.height, -1))
        layout = {
            "block_frames": block_frames,
            "n_frames": n,
            "n_blocks": (n + block_frames - 1) // block_frames,
            "arrays": {s.path: list(s.frame_shape) for s in arrays},
            "static_checksums": static_sums,
        }
        group.attrs.update({"layout": layout, "initialized": True})
        return cls(path, root=root, key=key)

    @staticmethod
    def _write_static(group: zarr.Group, name: str, values: np.ndarray) -> str:
        zarr_chunks = (min(max(values.shape[0], 1), 1 << 16), *values.shape[1:])
        arr = group.create_array(name, shape=values.shape, dtype=values.dtype, chunks=zarr_chunks,
                                 compressors=_compressor(values.dtype.itemsize), fill_value=0)
        arr[...] = values
        return _sha256(values)

    # ------------------------------------------------------------------ properties
    @property
    def attrs(self) -> dict[str, Any]:
        """The group attributes: as opened until the group is used, then the group's own (they change when
        this process writes them)."""
        return dict(self.group.attrs) if "group" in self.__dict__ else dict(self._opened_attrs)

    @property
    def key(self) -> str:
        return self._key

    @property
    def layout(self) -> dict[str, Any]:
        return dict(self.attrs.get("layout", {}))

    @property
    def initialized(self) -> bool:
        return bool(self.attrs.get("initialized", False))

    @property
    def complete(self) -> bool:
        return bool(self.attrs.get("complete", False))

    @property
    def n_frames(self) -> int:
        return int(self.layout["n_frames"])

    def block_range(self, block: int) -> tuple[int, int]:
        bf = int(self.layout["block_frames"])
        return block * bf, min((block + 1) * bf, self.n_frames)

    def matches(self, manifest: Manifest) -> bool:
        """Whether this cache holds exactly what `manifest` asks for."""
        return identity_of(self.manifest.to_dict()) == identity_of(manifest.to_dict())

    def dataset_difference(self, identity: Mapping[str, Any]) -> IdentityDifference | None:
        """The first file where the dataset this cache was extracted from differs from `identity`
        (a dataset's current `dataset_identity`), or None when they are the same dataset."""
        return compare_identity(self.manifest.dataset_identity, identity)

    def check_dataset(self, identity: Mapping[str, Any], dataset: str | None = None) -> None:
        """Raise CacheError (one line, naming the first differing file) unless this cache was extracted
        from the dataset whose current identity is `identity`. For every use of an existing cache with
        a dataset: resuming an extraction, sharing a cache."""
        diff = self.dataset_difference(identity)
        if diff is not None:
            recorded = self.manifest.dataset.source
            raise CacheError(f"cache {self.key} does not match dataset {dataset or recorded}: it was extracted "
                             f"from {recorded} with different content; first differing file: {diff}")

    # ------------------------------------------------------------------ writing
    def _marker(self, block: int) -> str:
        return f"{self.key}/{PROGRESS_DIR}/block-{block:06d}.json"

    def blocks_done(self) -> set[int]:
        """Blocks with a durable marker (their data was fully written before the marker)."""
        if self.complete:
            return set(range(int(self.layout["n_blocks"])))
        return {int(rel.rsplit("-", 1)[1].split(".")[0])
                for rel in self.root.sizes(f"{self.key}/{PROGRESS_DIR}/") if rel.endswith(".json")}

    def write_block(self, block: int, data: Mapping[str, np.ndarray]) -> None:
        """Write every feature array's slice for `block`, then its checksum marker (atomically)."""
        start, stop = self.block_range(block)
        expected = set(self.layout["arrays"])
        if set(data) != expected:
            raise CacheError(f"{self.path}: block {block} got arrays {sorted(data)}, expected {sorted(expected)}")
        sums = {}
        for name, values in data.items():
            if values.shape[0] != stop - start:
                raise CacheError(f"{self.path}: block {block} of {name} has {values.shape[0]} frames, "
                                 f"expected {stop - start}")
            self.group[name][start:stop] = values
            sums[name] = _sha256(values)
        self.root.put(self._marker(block), json.dumps(sums).encode())

    def finalize(self) -> None:
        """Mark complete: requires a marker for every block; moves checksums into the attributes."""
        n_blocks = int(self.layout["n_blocks"])
        missing = sorted(set(range(n_blocks)) - self.blocks_done())
        if missing:
            raise CacheError(f"{self.path}: cannot mark complete, blocks {missing[:5]} not written")
        sums: dict[str, list[str]] = {name: [] for name in self.layout["arrays"]}
        for block in range(n_blocks):
            per = json.loads(self.root.get(self._marker(block)))
            for name in sums:
                sums[name].append(per[name])
        # what killed writers left half-written (their blocks were rewritten since): a complete cache holds exactly
        # the files of an uninterrupted run, and push never copies the leftovers
        self.root.delete([rel for rel in self.root.sizes(f"{self.key}/") if rel.endswith(PARTIAL_SUFFIX)])
        self.group.attrs.update({
            "checksums": sums,
            "complete": True,
            "completed_at": datetime.now(UTC).isoformat(timespec="seconds"),
        })
        self.root.delete_prefix(f"{self.key}/{PROGRESS_DIR}/")

    # ------------------------------------------------------------------ reading
    def feature_path(self, camera: str, name: str) -> str:
        path = f"features/{camera}/{name}"
        if path not in self.layout.get("arrays", {}):
            have = sorted(self.layout.get("arrays", {}))
            raise CacheError(f"{self.key}: no array {path!r}; this cache has {have}")
        return path

    def read_features(self, camera: str, name: str, rows: np.ndarray | slice | None = None) -> torch.Tensor:
        """Features of `camera` at grid/extra `name` ('8x8', 'connector'), as a tensor in stored precision."""
        path = self.feature_path(camera, name)
        if rows is None:
            rows = np.arange(self.n_frames)
        elif isinstance(rows, slice):
            rows = np.arange(self.n_frames)[rows]
        return from_storage(self._read_rows(path, np.asarray(rows)), self.manifest.storage_dtype)

    def _read_rows(self, name: str, rows: np.ndarray) -> np.ndarray:
        """`arr[rows]` read one block at a time, each block checked against its checksum the first time this
        handle's reader reads it (whole, which is what the checksum covers); later reads take the rows' span only.

        zarr's orthogonal selection over block files costs time per block file in zarr chunk bookkeeping
        (docs/measured.md); slicing inside each block file and indexing in numpy reads the same bytes and holds at
        most one block beyond the result in memory.
        """
        arr = self.group[name]
        out = np.empty((len(rows), *arr.shape[1:]), dtype=arr.dtype)
        order = np.argsort(rows, kind="stable")
        ordered = rows[order]
        blocks = ordered // int(self.layout["block_frames"])
        wanted_blocks = [int(b) for b in np.unique(blocks)]
        self.root.fetch(self.key, [f"{name}/{arr.metadata.encode_chunk_key((b,) + (0,) * (arr.ndim - 1))}"
                                   for b in wanted_blocks])
        for block in wanted_blocks:
            sel = blocks == block
            wanted = ordered[sel]
            if self.complete and (str(self.path), name, block) not in self.checks:
                lo, hi = self.block_range(block)
                values = self._checked_block(arr, name, block)
            else:
                lo, hi = int(wanted[0]), int(wanted[-1]) + 1
                values = arr[lo:hi]
            out[order[sel]] = values[wanted - lo]
        return out

    def _checked_block(self, arr: zarr.Array, name: str, block: int) -> np.ndarray:
        start, stop = self.block_range(block)
        where = f"cache {self.path}: {name} frames {start}-{stop - 1} (block {block})"
        hint = f"run `graftcache verify {self.key}` to list every bad block, then extract or pull it again"
        try:
            values = arr[start:stop]
        except Exception as e:  # a damaged block file fails to decode
            raise CacheError(f"{where} is unreadable ({type(e).__name__}); {hint}") from None
        if _sha256(values) != self.attrs["checksums"][name][block]:
            raise CacheError(f"{where} does not match its stored checksum; {hint}")
        self.checks.add((str(self.path), name, block))
        return values

    def _static(self, name: str) -> np.ndarray:
        """A small whole array (index, low-dim, action stream), checked against its checksum once per reader."""
        values = self.group[name][...]
        expected = self.layout.get("static_checksums", {}).get(name)
        if self.complete and expected and (str(self.path), name, -1) not in self.checks:
            if _sha256(values) != expected:
                raise CacheError(f"cache {self.path}: {name} does not match its stored checksum; "
                                 f"run `graftcache verify {self.key}`")
            self.checks.add((str(self.path), name, -1))
        return values

    def action_stream(self) -> pl.DataFrame:
        """Every frame's action of the cached episodes at the dataset's full rate (episode_index,
        frame_index, action), for action chunks."""
        values = self._static(f"{ACTION_STREAM}/action")
        return pl.DataFrame({name: self._static(f"{ACTION_STREAM}/{name}")
                             for name in ("episode_index", "frame_index")}).with_columns(
            pl.Series("action", values, dtype=pl.Array(pl.Float32, values.shape[1])))

    def index(self) -> pl.DataFrame:
        """Per-frame index and low-dim columns, in cache order."""
        cols = {name: self._static(f"index/{name}")
                for name in ("index", "episode_index", "frame_index", "task_index", "suite_index")}
        cols["timestamp"] = self._static("lowdim/timestamp")
        df = pl.DataFrame(cols)
        for name in ("state", "action"):
            values = self._static(f"lowdim/{name}")
            df = df.with_columns(pl.Series(name, values, dtype=pl.Array(pl.Float32, values.shape[1])))
        return df

    # ------------------------------------------------------------------ checking
    def verify(self) -> list[str]:
        """Re-read every block and static array and compare with the stored checksums.

        Returns a list of problems (empty = the cache is complete and intact).
        """
        if not self.initialized:
            return [f"{self.key}: initialisation never finished"]
        if not self.complete:
            todo = int(self.layout["n_blocks"]) - len(self.blocks_done())
            return [f"{self.key}: incomplete ({todo} of {self.layout['n_blocks']} blocks not written)"]
        return [p for _, p in self.damage(self.attrs["checksums"])]

    def damage(self, checksums: Mapping[str, list[str]]) -> list[tuple[str, str]]:
        """(object, problem) for every static array and feature block that does not read back as the layout's
        static checksums and `checksums` (the feature blocks') say; the object (a block file, or a static array's
        folder ending in '/') is what to fetch again."""
        problems = []
        for name, expected in self.layout["static_checksums"].items():
            try:
                got = _sha256(self.group[name][...])
            except Exception as e:  # a damaged zarr chunk fails to decode
                problems.append((f"{name}/", f"{self.key}: {name} unreadable ({type(e).__name__})"))
                continue
            if got != expected:
                problems.append((f"{name}/", f"{self.key}: {name} checksum mismatch"))
        for name, sums in checksums.items():
            arr = self.group[name]
            for block, expected in enumerate(sums):
                start, stop = self.block_range(block)
                block_file = f"{name}/{arr.metadata.encode_chunk_key((block,) + (0,) * (arr.ndim - 1))}"
                try:
                    got = _sha256(arr[start:stop])
                except Exception as e:  # a corrupt block file fails to decode
                    problems.append((block_file, f"{self.key}: {name} frames {start}-{stop - 1} unreadable "
                                                 f"(block {block}, {block_file}; {type(e).__name__}: "
                                                 f"{' '.join(str(e).split())})"))
                    continue
                if got != expected:
                    problems.append((block_file, f"{self.key}: {name} frames {start}-{stop - 1} checksum mismatch "
                                            f"(block {block}, {block_file})"))
        return problems

    def size_bytes(self) -> int:
        return sum(self.root.sizes(f"{self.key}/").values())


@dataclass(frozen=True)
class BrokenCache:
    """A folder under a root that looks like a cache (it has a zarr.json) but cannot be opened."""

    key: str
    reason: str


def scan_caches(root: str | Path | Root) -> tuple[list[FeatureCache], list[BrokenCache]]:
    """Every cache under `root` (sorted by key), opened read-only, and those that cannot be opened (a corrupt
    zarr.json or manifest), each with the one-line reason; folders without zarr.json are not caches."""
    root = open_root(root)
    good, broken = [], []
    for key in root.keys():
        try:
            good.append(FeatureCache.in_root(root, key))
        except CacheError as e:
            broken.append(BrokenCache(key, str(e)))
    return good, broken


def list_caches(root: str | Path | Root) -> list[FeatureCache]:
    """The caches under `root` that open (sorted by key); broken ones are left out (`scan_caches` names them)."""
    return scan_caches(root)[0]
