"""Weight provenance and offline resolution shared by the builders.

Nothing here downloads: a hub id is looked up in the local Hugging Face cache (read at call time,
so tests and CLIs can redirect it) and the files found there are what gets loaded and hashed. The
sha256 recorded in the manifest is always of the bytes actually used: the weights file(s), or for a
random init the state_dict tensors themselves.
"""

from __future__ import annotations

import contextlib
import json
from collections.abc import Iterable, Iterator, Mapping
from pathlib import Path

import torch
from safetensors import SafetensorError
from safetensors.torch import load_file

from graftcache.encoders.spec import EncoderSpec
from graftcache.errors import EncoderError, first_line
from graftcache.hashing import sha256_bytes, sha256_file, sha256_tensors
from graftcache.hub_cache import repo_dir

# transformers' own preference order: safetensors (one file, or several listed by an index) before pickled .bin.
HF_WEIGHT_FILES = ("model.safetensors", "model.safetensors.index.json", "pytorch_model.bin",
                   "pytorch_model.bin.index.json")


def sha256_files(paths: Iterable[Path]) -> str:
    """One file: its sha256. Several (a checkpoint split over files): sha256 of the "name sha256" lines, by name."""
    paths = sorted(paths, key=lambda p: p.name)
    if len(paths) == 1:
        return sha256_file(paths[0])
    lines = "".join(f"{p.name} {sha256_file(p)}\n" for p in paths)
    return sha256_bytes(lines.encode())


def sha256_state_dict(state: Mapping[str, torch.Tensor]) -> str:
    """Hash of tensors in key order (name, dtype, shape and raw bytes), for weights that have no file."""
    return sha256_tensors(state.items(), header_end="\n")


@contextlib.contextmanager
def seeded(seed: int) -> Iterator[None]:
    """Deterministic parameter init (same seed -> identical weights) without disturbing the caller's RNG."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        yield


def hub_snapshot(repo_id: str) -> tuple[Path, str] | None:
    """The cached snapshot folder of a model repo (refs/main, else a single snapshot) and its revision."""
    folder = repo_dir(repo_id)
    ref = folder / "refs" / "main"
    if ref.is_file():
        rev = ref.read_text().strip()
        if (folder / "snapshots" / rev).is_dir():
            return folder / "snapshots" / rev, rev
    snaps = sorted(p for p in (folder / "snapshots").glob("*") if p.is_dir()) if folder.is_dir() else []
    return (snaps[0], snaps[0].name) if len(snaps) == 1 else None


def hf_weight_files(folder: Path) -> list[Path]:
    """The weight file(s) transformers would load from a model folder (shards listed by the index)."""
    for name in HF_WEIGHT_FILES:
        path = folder / name
        if path.is_file():
            if name.endswith(".index.json"):
                shards = sorted(set(json.loads(path.read_text())["weight_map"].values()))
                return [folder / s for s in shards]
            return [path]
    return []


def missing_hub_weights(spec: EncoderSpec, repo_id: str, what: str) -> EncoderError:
    """The one error for "the default weights are not on this machine", with the ways out."""
    where = repo_dir(repo_id)
    return EncoderError(f"encoder {spec.name!r}: {what} for hub repo {repo_id!r} not found in the local Hugging "
                        f"Face cache ({where}); nothing is downloaded. Put the model there (e.g. `hf download "
                        f"{repo_id}` where there is network), or pass --weights PATH, or --random-init")


def require_file(spec: EncoderSpec, path: Path, suffixes: tuple[str, ...] = (".safetensors",)) -> Path:
    """A user-given weights file must exist and be of a format that cannot execute code."""
    if not path.is_file():
        raise EncoderError(f"encoder {spec.name!r}: weights file {path} does not exist")
    if path.suffix not in suffixes:
        raise EncoderError(f"encoder {spec.name!r}: weights file {path} must be {' or '.join(suffixes)} "
                           f"(pickled checkpoints are not loaded; convert with safetensors.torch.save_file)")
    return path


def read_safetensors(spec: EncoderSpec, path: Path) -> dict[str, torch.Tensor]:
    """The tensors of a safetensors file; a file that is not one is a one-line error naming it."""
    try:
        return load_file(path)
    except SafetensorError as e:
        raise EncoderError(f"encoder {spec.name!r}: {path} is not a safetensors file ({first_line(e)})") from None


def key_mismatch(expected: Mapping[str, torch.Tensor], found: Mapping[str, torch.Tensor],
                 error: BaseException | None = None, shown: int = 3) -> str:
    """'N missing (first: ...), M unexpected (first: ...), K mis-shaped (...)' between a model's state dict and
    a checkpoint's tensors; `error`'s first line when the keys agree (a checkpoint filter failed instead)."""
    missing = [k for k in expected if k not in found]
    unexpected = [k for k in found if k not in expected]
    shaped = [f"{k} {tuple(found[k].shape)} vs {tuple(v.shape)}" for k, v in expected.items()
              if k in found and tuple(found[k].shape) != tuple(v.shape)]
    parts = [f"{len(keys)} {what} (first: {', '.join(keys[:shown])})"
             for what, keys in (("missing", missing), ("unexpected", unexpected), ("mis-shaped", shaped)) if keys]
    if parts:
        return "; ".join(parts)
    return first_line(error) if error is not None else "keys and shapes agree"
