"""What a LeRobot dataset contains, independent of its codebase version and storage.

`DatasetMeta` is the one description every later stage (extract, store manifest, fit) relies on;
the version readers (v2.py, v3.py) only differ in where they find it. Feature parsing lives here
because meta/info.json `features` has the same shape in v2.0, v2.1 and v3.0.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from graftcache.errors import DatasetError

#: Feature keys tried, in order, for the proprioceptive state and the action.
STATE_KEYS = ("observation.state", "state")
ACTION_KEYS = ("action", "actions")
#: Prefixes stripped from a camera feature key to get its short name.
CAMERA_PREFIXES = ("observation.images.", "observation.")
#: Feature dtypes that hold camera frames: "video" (mp4 files) or "image" (PNG bytes in parquet).
CAMERA_DTYPES = ("video", "image")
_CHANNEL_NAMES = ("channel", "channels", "c")


@dataclass(frozen=True)
class EpisodeMeta:
    """One episode: its id, frame count, (first) task and the global index of its first frame; `task_indices`
    every task its metadata lists (first = task_index), which its frames' task_index must come from."""

    index: int
    length: int
    task_index: int
    dataset_from_index: int
    task_indices: tuple[int, ...] = ()

    @property
    def tasks_listed(self) -> tuple[int, ...]:
        return self.task_indices or (self.task_index,)


@dataclass(frozen=True)
class DatasetMeta:
    """Everything downstream needs to know about a dataset without touching its frames."""

    source: str
    root: Path
    repo_id: str | None
    revision: str | None
    codebase_version: str
    fps: float
    cameras: tuple[str, ...]
    camera_keys: dict[str, str]
    camera_storage: dict[str, str]  # short name -> "video" (mp4) | "image" (PNG bytes in parquet)
    image_shape: dict[str, tuple[int, int, int]]
    state_key: str
    action_key: str
    state_dim: int
    action_dim: int
    tasks: tuple[str, ...]
    episodes: tuple[EpisodeMeta, ...]
    n_frames: int
    identity_files: tuple[Path, ...]  # metadata files, then every data parquet and mp4 the episodes use

    @functools.cached_property
    def content_identity(self) -> dict[str, dict[str, dict[str, int | str]]]:
        """{"files": {path relative to root: {"size", "sha256"}}} over `identity_files` (see identity.py).

        Computed on first use, not when the dataset is opened: the first time a dataset is seen this
        reads every byte of it; later runs reuse the remembered hashes of unchanged files.
        """
        from graftcache.datasets.identity import content_identity

        return content_identity(self.root, self.identity_files)

    @property
    def identity(self) -> dict[str, Any]:
        """What a cache manifest records as `dataset_identity`: the format version and the content."""
        return {"codebase_version": self.codebase_version, **self.content_identity}


@dataclass(frozen=True)
class Features:
    """The parts of meta/info.json `features` graftcache reads."""

    cameras: tuple[str, ...]
    camera_keys: dict[str, str]
    camera_storage: dict[str, str]
    image_shape: dict[str, tuple[int, int, int]]
    state_key: str
    action_key: str
    state_dim: int
    action_dim: int


def parse_features(info: dict[str, Any], info_path: Path) -> Features:
    """Cameras (short name -> key, storage, HWC shape) and the state/action columns of a dataset."""
    feats: dict[str, dict[str, Any]] = info.get("features") or {}
    camera_keys: dict[str, str] = {}
    storage: dict[str, str] = {}
    shapes: dict[str, tuple[int, int, int]] = {}
    for key, ft in feats.items():
        if ft.get("dtype") not in CAMERA_DTYPES:
            continue
        short = _short_name(key)
        if short in camera_keys:
            raise DatasetError(f"{info_path}: camera features {camera_keys[short]!r} and {key!r} share the "
                               f"short name {short!r}")
        camera_keys[short] = key
        storage[short] = ft["dtype"]
        shapes[short] = _hwc(key, ft, info_path)
    state_key = _first_present(STATE_KEYS, feats, "state", info_path)
    action_key = _first_present(ACTION_KEYS, feats, "action", info_path)
    return Features(
        cameras=tuple(camera_keys),
        camera_keys=camera_keys,
        camera_storage=storage,
        image_shape=shapes,
        state_key=state_key,
        action_key=action_key,
        state_dim=_vector_dim(state_key, feats[state_key], info_path),
        action_dim=_vector_dim(action_key, feats[action_key], info_path),
    )


def _short_name(key: str) -> str:
    for prefix in CAMERA_PREFIXES:
        if key.startswith(prefix):
            return key[len(prefix):]
    return key


def _hwc(key: str, ft: dict[str, Any], info_path: Path) -> tuple[int, int, int]:
    """(H, W, 3) from a feature's shape; channel-first declarations are recognised by their names."""
    shape = tuple(int(s) for s in ft.get("shape", ()))
    if len(shape) != 3:
        raise DatasetError(f"{info_path}: camera feature {key!r} has shape {list(shape)}, expected 3 dims")
    names = [str(n).lower() for n in (ft.get("names") or [])]
    h, w, c = (shape[1], shape[2], shape[0]) if names[:1] and names[0] in _CHANNEL_NAMES else shape
    if c != 3:
        raise DatasetError(f"{info_path}: camera feature {key!r} has {c} channels; only RGB is supported")
    return (h, w, c)


def _first_present(candidates: tuple[str, ...], feats: dict[str, Any], what: str, info_path: Path) -> str:
    for key in candidates:
        if key in feats:
            return key
    raise DatasetError(f"{info_path}: no {what} feature (looked for {', '.join(candidates)}); "
                       f"features are {', '.join(feats)}")


def _vector_dim(key: str, ft: dict[str, Any], info_path: Path) -> int:
    shape = [int(s) for s in ft.get("shape", ())]
    if len(shape) != 1:
        raise DatasetError(f"{info_path}: feature {key!r} has shape {shape}, expected a vector")
    return shape[0]
