"""A cache's manifest as a typed record, the format version, and the one way caches of older formats are read.

The manifest is what a cache says it holds and how it was made. Its identity fields (graftcache.store.key)
decide the cache key; everything else is provenance. It is stored as JSON in the group attributes
(`Manifest.to_dict`) and read back through `Manifest.read`, which is the only place that knows older formats:
a manifest of format 1 that records everything later formats do, and one of format 2, are upgraded in memory
(`upgrade`: their keys renamed as `RENAMED` declares; the cache's key, the hash of what is stored in its own
format, stays its folder's name: `stored_key`); one made before a record existed is refused in one line that
names the cache and gives the `graftcache extract` command that rebuilds it. No other module branches on a
cache's age.
"""

from __future__ import annotations

import dataclasses
import functools
import types
import typing
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
from typing import Any

from graftcache.store.key import IDENTITY_FIELDS, RefusedPlace, cache_key

FORMAT_VERSION = 3
#: Manifest keys of formats 1 and 2 -> their format 3 names (one word per idea), the one rename map
#: `upgrade` and `stored_key` apply; the values are unchanged.
RENAMED = {
    "native_grid": "unpooled_grid",
    "dtype": "storage_dtype",
    "dataset_fingerprint": "dataset_identity",
}
#: What format 1 manifests may lack, in the order graftcache began recording it: (field as format 1 named it,
#: what it records). A format 1 manifest holding all of them is format 2 but for its version; one lacking any
#: cannot be upgraded.
PREVIOUS_GAPS = (
    ("frame_stride", "frame strides"),
    ("native_grid", "unpooled grids"),
    ("numerics", "numerics fingerprints"),
    ("dataset_fingerprint.files", "content identities"),
)


class UnreadableManifest(RefusedPlace):
    """A cache whose manifest this graftcache cannot read: of an older format it cannot upgrade, or not of the
    shape its format says. Listed as broken, never used, and never replaced or deleted as an unfinished cache."""


@dataclass(frozen=True)
class DatasetRecord:
    """Where the cached frames came from (provenance: the content identity is `Manifest.dataset_identity`)."""

    source: str                   # as the user named it (folder or hub id)
    root: str                     # the folder it was read from
    repo_id: str | None
    revision: str | None
    codebase_version: str
    fps: float
    n_episodes_total: int
    n_frames_total: int


@dataclass(frozen=True)
class Manifest:
    """Everything a cache records about itself (see graftcache.extract for how each field is filled)."""

    format_version: int
    graftcache_version: str
    created_at: str
    dataset: DatasetRecord
    dataset_identity: dict[str, Any]         # the dataset's content identity (graftcache.datasets.identity)
    episodes: list[int] | None               # None: every episode
    frame_stride: int                        # features of every k-th frame of each episode
    cameras: list[str]
    camera_keys: dict[str, str]              # camera -> the dataset's feature key
    encoder: dict[str, Any]                  # the encoder's own description (name, width, grid, recipe)
    weights: dict[str, Any]                  # where its weights came from
    weights_sha256: str
    random_init: bool
    grids: list[str]                         # stored grids, resolved ("16x16", never "unpooled")
    unpooled_grid: str | None                # which of them is the encoder's own grid, unpooled; None: only pooled
    extras: dict[str, list[int]]             # extra token arrays of native towers -> one frame's shape
    storage_dtype: str                       # the dtype features are stored in
    compute_dtype: str                       # resolved ("bf16" | "fp32"), never "auto"
    n_frames: int
    tasks: list[str]
    suites: list[str]                        # `suite_index` counts in this list
    state_key: str | None
    action_key: str | None
    versions: dict[str, str]                 # libraries that computed the features
    numerics: dict[str, Any]                 # the numerics fingerprint (graftcache.encoders.fingerprint)
    run: dict[str, Any]                      # device, batch size, workers, command line
    extra: dict[str, Any] = field(default_factory=dict)  # the request's extra_manifest

    @property
    def encoder_name(self) -> str:
        return str(self.encoder["name"])

    @property
    def trained_by(self) -> str | None:
        """What trained the encoder's weights when they are neither released nor random-init: "train-tiny" for the
        tower of a tiny policy it trained (`weights.trained_by`). None for every other cache, and for such towers'
        caches written before it was recorded, whose `random_init` is true for both facts."""
        return self.weights.get("trained_by")

    @property
    def unreleased(self) -> bool:
        """The encoder's weights are no released pretraining: random-init, or a tower train-tiny trained. Results
        rows record it as `encoder_random_init` (graftcache.results.SCHEMA: a tiny policy's tower says True, trained
        or not), where the manifest, the log and the report say which of the two it is."""
        return bool(self.random_init or self.trained_by)

    @property
    def weights_label(self) -> str:
        """The encoder's weights in a word: "trained by train-tiny", "random-init", else their source."""
        if self.trained_by is not None:
            return f"trained by {self.trained_by}"
        return "random-init" if self.random_init else str(self.weights.get("source", "?"))

    def to_dict(self) -> dict[str, Any]:
        """The JSON form stored in the group attributes (and hashed into the key)."""
        return asdict(self)

    @classmethod
    def read(cls, raw: Mapping[str, Any], where: str, key: str) -> Manifest:
        """The manifest stored as `raw` (of cache `key` at `where`), upgraded from format 1 if it must be."""
        if not isinstance(raw, Mapping):
            raise UnreadableManifest(f"{where}: the manifest is a {type(raw).__name__}, not a mapping")
        raw = upgrade(raw, where, key)
        fields = {f.name for f in dataclasses.fields(cls)}
        missing = sorted(fields - set(raw) - {"extra"})
        unknown = sorted(set(raw) - fields)
        if missing or unknown:
            raise UnreadableManifest(f"{where}: manifest of format {FORMAT_VERSION} "
                             f"{'lacks ' + ', '.join(missing) if missing else 'has unknown ' + ', '.join(unknown)}")
        values = {**raw, "dataset": _record(raw["dataset"], where)}
        _check_types(cls, values, where)
        if not isinstance(values["encoder"].get("name"), str):
            raise UnreadableManifest(f"{where}: manifest field encoder has no name")
        return cls(**values)


def upgrade(raw: Mapping[str, Any], where: str, key: str) -> dict[str, Any]:
    """The one upgrade path: a stored manifest of format 1 or 2 as format 3 (keys renamed as `RENAMED` says; of
    format 1, fields outside the format move into `extra`), format 3 as it is; anything else is refused
    (UnreadableManifest) naming the cache and the command that rebuilds it."""
    version = raw.get("format_version")
    if version == FORMAT_VERSION:
        return dict(raw)
    if version not in (1, 2):
        _refuse(raw, where, key, f"it is of format {version!r}, which this graftcache does not read")
    if version == 1:
        for name, what in PREVIOUS_GAPS:
            head, _, sub = name.partition(".")
            if head not in raw or (sub and sub not in (raw[head] or {})):
                _refuse(raw, where, key, f"it was made before graftcache recorded {what} (format 1)")
    renamed = {RENAMED.get(k, k): v for k, v in raw.items()}
    fields = {f.name for f in dataclasses.fields(Manifest)}
    return {**{k: v for k, v in renamed.items() if k in fields}, "format_version": FORMAT_VERSION,
            "extra": {**{k: v for k, v in renamed.items() if k not in fields}, **(renamed.get("extra") or {})}}


def stored_key(raw: Mapping[str, Any]) -> str:
    """The key a stored manifest hashes to in its own format's names (what its folder is named by): formats 1
    and 2 hashed their identity fields under the names `RENAMED` has since replaced. KeyError or TypeError when
    it lacks an identity field (a format older than any `upgrade` reads, refused there)."""
    if raw.get("format_version") == FORMAT_VERSION:
        return cache_key(raw)
    former = {new: old for old, new in RENAMED.items()}
    return cache_key(raw, tuple(former.get(f, f) for f in IDENTITY_FIELDS))


def rebuild_command(raw: Mapping[str, Any]) -> str:
    """The `graftcache extract` command that makes, in this format, the cache a manifest (of any format)
    describes."""
    raw = {RENAMED.get(k, k): v for k, v in raw.items()}
    enc, weights = raw.get("encoder") or {}, raw.get("weights") or {}
    parts = ["graftcache extract", f"--encoder {enc.get('name', 'ENCODER')}",
             f"--dataset {(raw.get('dataset') or {}).get('source', 'DATASET')}"]
    source, ref = weights.get("source"), weights.get("ref")
    if source == "random-init":
        parts.append(f"--random-init --seed {weights.get('seed', 0)}")
    elif source in ("file", "policy") and ref:
        parts.append(f"--{'weights' if source == 'file' else 'policy'} {ref}")
    if raw.get("grids"):
        parts.append(f"--grids {','.join(raw['grids'])}")
    if raw.get("cameras"):
        parts.append(f"--cameras {','.join(raw['cameras'])}")
    if raw.get("episodes"):
        parts.append(f"--episodes {','.join(map(str, raw['episodes']))}")
    if (raw.get("frame_stride") or 1) > 1:
        parts.append(f"--frame-stride {raw['frame_stride']}")
    for flag, name in (("--storage-dtype", "storage_dtype"), ("--compute-dtype", "compute_dtype")):
        if raw.get(name):
            parts.append(f"{flag} {raw[name]}")
    return " ".join(parts)


def _refuse(raw: Mapping[str, Any], where: str, key: str, why: str) -> typing.NoReturn:
    raise UnreadableManifest(f"cache {key} ({where}): {why}; graftcache reads caches of format {FORMAT_VERSION} "
                             f"and the format 1 and 2 caches made since; rebuild it: {rebuild_command(raw)}")


def _record(raw: Any, where: str) -> DatasetRecord:
    names = {f.name for f in dataclasses.fields(DatasetRecord)}
    if not isinstance(raw, Mapping) or set(raw) != names:
        got = sorted(raw) if isinstance(raw, Mapping) else type(raw).__name__
        raise UnreadableManifest(f"{where}: manifest field dataset is {got}, not the fields {sorted(names)}")
    values = dict(raw)
    _check_types(DatasetRecord, values, where, "dataset.")
    return DatasetRecord(**values)


@functools.cache
def _hints(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def _check_types(cls: type, values: Mapping[str, Any], where: str, prefix: str = "") -> None:
    """UnreadableManifest naming the first field whose value is not of its declared type (outer types only)."""
    hints = _hints(cls)
    for name, value in values.items():
        hint = hints[name]
        allowed = typing.get_args(hint) if isinstance(hint, types.UnionType) else (hint,)
        outer = tuple(typing.get_origin(a) or a for a in allowed if a is not Any)
        outer = tuple(type(None) if a is None else a for a in outer)
        if float in outer:
            outer += (int,)
        if outer and not isinstance(value, outer) or (isinstance(value, bool) and bool not in outer):
            wanted = " or ".join(getattr(a, "__name__", str(a)) for a in allowed)
            raise UnreadableManifest(f"{where}: manifest field {prefix}{name} is {value!r}, not {wanted}")
