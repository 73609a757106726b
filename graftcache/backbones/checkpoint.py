"""Finding, loading and checking policy checkpoints (local folders or the Hugging Face cache, offline).

Why a separate check after lerobot's `from_pretrained`: SmolVLA loads with `strict=False` (missing
keys are only logged) and pi0.5 wraps its strict load in a try/except that prints a warning and
returns a partly random model. A measurement tool must not score a silently random backbone, so
every load is followed by a key/shape comparison against the safetensors file.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import logging
import os
from collections.abc import Callable, Iterator
from pathlib import Path

import torch
from torch import nn

from graftcache.errors import BackboneError

WEIGHTS_FILE = "model.safetensors"
PREPROCESSOR_FILE = "policy_preprocessor.json"
POSTPROCESSOR_FILE = "policy_postprocessor.json"


def hub_cache_dir() -> Path:
    """The HF hub cache as the environment says now (huggingface_hub reads it only at import)."""
    if os.environ.get("HF_HUB_CACHE"):
        return Path(os.environ["HF_HUB_CACHE"])
    home = os.environ.get("HF_HOME") or Path.home() / ".cache" / "huggingface"
    return Path(home) / "hub"


def cached_repo(repo_id: str, what: str) -> Path:
    """Snapshot folder of `repo_id` in the local HF cache; BackboneError naming what was looked for."""
    from huggingface_hub import snapshot_download
    from huggingface_hub.errors import HFValidationError, LocalEntryNotFoundError

    cache = hub_cache_dir()
    try:
        return Path(snapshot_download(repo_id=repo_id, cache_dir=cache, local_files_only=True))
    except (LocalEntryNotFoundError, HFValidationError, OSError):
        raise BackboneError(
            f"{what} {repo_id!r} is neither a local folder nor in the Hugging Face cache {cache} "
            f"(looked for {cache / ('models--' + repo_id.replace('/', '--'))}); download it first"
        ) from None


def resolve_source(source: str | Path, what: str = "policy checkpoint") -> Path:
    """A local checkpoint folder as given, or a hub id resolved to its cached snapshot folder."""
    path = Path(source).expanduser()
    if path.is_dir():
        return path
    if path.exists() or str(source).startswith((".", "/", "~")) or str(source).count("/") != 1:
        raise BackboneError(f"{what} {str(source)!r}: no such folder, and not a hub id of the form org/name")
    return cached_repo(str(source), what)


def weights_file(folder: Path) -> Path:
    path = folder / WEIGHTS_FILE
    if not path.is_file():
        raise BackboneError(f"{folder}: no {WEIGHTS_FILE} (not a lerobot policy checkpoint)")
    return path


@contextlib.contextmanager
def quiet() -> Iterator[None]:
    """Silence lerobot's construction/loading chatter (print() and root-logger warnings)."""
    previous = logging.root.manager.disable
    logging.disable(logging.WARNING)
    try:
        with contextlib.redirect_stdout(io.StringIO()):
            yield
    finally:
        logging.disable(previous)


def verify_weights(policy: nn.Module, file: Path, key_map: Callable[[dict], dict] = dict) -> None:
    """Raise BackboneError unless every policy tensor has a same-shaped entry in the checkpoint.

    `key_map` turns {file key: shape} into {policy key: shape} (pi0.5 renames openpi keys). A tensor
    tied to another (same storage) may be absent from the file: safetensors stores shared tensors once.
    """
    from safetensors import safe_open

    with safe_open(str(file), framework="pt") as f:
        shapes = key_map({k: tuple(f.get_slice(k).get_shape()) for k in f.keys()})
    state = policy.state_dict()
    present_storage = {state[k].data_ptr() for k in state if k in shapes}
    missing = [k for k in state if k not in shapes and state[k].data_ptr() not in present_storage]
    wrong = [f"{k} {tuple(state[k].shape)} vs {shapes[k]}" for k in state
             if k in shapes and tuple(state[k].shape) != tuple(shapes[k])]
    if missing or wrong:
        detail = "; ".join([*(f"missing {k}" for k in missing[:3]), *(f"shape {w}" for w in wrong[:3])])
        raise BackboneError(
            f"{file}: checkpoint does not match the policy ({len(missing)} missing, {len(wrong)} mis-shaped): {detail}"
        )


def load_processors(folder: Path, pre_overrides: dict, post_overrides: dict):
    """lerobot's saved pre/post processor pipelines of a checkpoint folder, or None if it has none."""
    from lerobot.processor import PolicyProcessorPipeline
    from lerobot.processor.converters import (
        batch_to_transition,
        policy_action_to_transition,
        transition_to_batch,
        transition_to_policy_action,
    )

    if not (folder / PREPROCESSOR_FILE).is_file() or not (folder / POSTPROCESSOR_FILE).is_file():
        return None
    try:
        pre = PolicyProcessorPipeline.from_pretrained(
            folder, config_filename=PREPROCESSOR_FILE, overrides=pre_overrides,
            to_transition=batch_to_transition, to_output=transition_to_batch,
        )
        post = PolicyProcessorPipeline.from_pretrained(
            folder, config_filename=POSTPROCESSOR_FILE, overrides=post_overrides,
            to_transition=policy_action_to_transition, to_output=transition_to_policy_action,
        )
    except (OSError, ValueError, KeyError) as exc:
        raise BackboneError(f"{folder / PREPROCESSOR_FILE}: cannot load the policy processors ({exc})") from None
    return pre, post


def state_dict_sha256(module: nn.Module) -> str:
    """sha256 over (name, dtype, shape, bytes) of every state-dict tensor, in sorted name order."""
    digest = hashlib.sha256()
    for name, tensor in sorted(module.state_dict().items()):
        t = tensor.detach().to("cpu").contiguous()
        digest.update(f"{name}|{t.dtype}|{tuple(t.shape)}|".encode())
        digest.update(t.reshape(-1).view(torch.uint8).numpy())
    return digest.hexdigest()
