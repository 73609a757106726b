"""Finding policy checkpoints (local folders or the Hugging Face cache, offline), their processors and files.

The weights themselves are read by graftcache.backbones.lean_load, which also refuses a checkpoint that lacks a
tensor of the policy or shapes one differently.
"""

from __future__ import annotations

import contextlib
import io
import logging
import os
import stat
from collections.abc import Iterator
from pathlib import Path

from torch import nn

from graftcache.errors import BackboneError
from graftcache.hashing import sha256_tensors
from graftcache.hub_cache import hub_cache, repo_dir

WEIGHTS_FILE = "model.safetensors"
PREPROCESSOR_FILE = "policy_preprocessor.json"
POSTPROCESSOR_FILE = "policy_postprocessor.json"
#: Written into a checkpoint folder by devtools.released (random weights at a released policy's geometry).
RANDOM_MARKER = "graftcache_random_init.json"


def cached_repo(repo_id: str, what: str) -> Path:
    """Snapshot folder of `repo_id` in the local HF cache; BackboneError naming what was looked for."""
    from huggingface_hub import snapshot_download
    from huggingface_hub.errors import HFValidationError, LocalEntryNotFoundError

    cache = hub_cache()
    try:
        return Path(snapshot_download(repo_id=repo_id, cache_dir=cache, local_files_only=True))
    except (LocalEntryNotFoundError, HFValidationError, OSError):
        raise BackboneError(
            f"{what} {repo_id!r} is neither a local folder nor in the Hugging Face cache {cache} "
            f"(looked for {repo_dir(repo_id, cache=cache)}); download it first"
        ) from None


def local_or_cached(name: str, what: str) -> Path:
    """`name` as a local folder when it is one, else as a hub id's snapshot in the local HF cache: how lerobot's
    configs name the files a policy is built from beside its checkpoint (a VLM's config and processor, a
    tokenizer), which lerobot itself would download."""
    return Path(name) if Path(name).is_dir() else cached_repo(name, what)


def resolve_source(source: str | Path, what: str = "policy checkpoint") -> Path:
    """A local checkpoint folder as given, or a hub id resolved to its cached snapshot folder."""
    path = Path(source).expanduser()
    if path.is_dir():
        return check_readable(path, what)
    if path.exists() or str(source).startswith((".", "/", "~")) or str(source).count("/") != 1:
        raise BackboneError(f"{what} {str(source)!r}: no such folder, and not a hub id of the form org/name")
    return check_readable(cached_repo(str(source), what), what)


def check_readable(folder: Path, what: str = "policy checkpoint") -> Path:
    """`folder`, or a one-line BackboneError naming a file in it this user cannot read (e.g. a checkpoint
    another user saved 0600 into a shared root), instead of lerobot's misleading FileNotFoundError."""
    for p in sorted(folder.iterdir()):
        if p.is_file() and not os.access(p, os.R_OK):
            st = p.stat()
            raise BackboneError(f"{what} {p}: not readable by this user (mode {stat.filemode(st.st_mode)}, owner uid "
                                f"{st.st_uid}); its owner can run: chmod -R go+rX {folder}")
    return folder


def weights_file(folder: Path) -> Path:
    """The checkpoint's weights file, its safetensors header read, so a file that is not one is a one-line
    error naming it before lerobot loads it."""
    from safetensors import SafetensorError, safe_open

    path = folder / WEIGHTS_FILE
    if not path.is_file():
        raise BackboneError(f"{folder}: no {WEIGHTS_FILE} (not a lerobot policy checkpoint)")
    try:
        with safe_open(str(path), framework="pt"):
            pass
    except SafetensorError as e:
        raise BackboneError(f"{path}: not a safetensors file ({e})") from None
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


def is_random_release(folder: Path) -> bool:
    """Whether a checkpoint folder carries RANDOM_MARKER: random weights at the released geometry, written by
    devtools.released, so rows and manifests say random_init although no tiny marker is there."""
    return (folder / RANDOM_MARKER).is_file()


def state_dict_sha256(module: nn.Module) -> str:
    """sha256 over (name, dtype, shape, bytes) of every state-dict tensor, in sorted name order."""
    return sha256_tensors(sorted(module.state_dict().items()), header_end="|")


def current_umask() -> int:
    """The process umask, read without changing it where the kernel reports it (Linux /proc)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    mask = os.umask(0o022)  # elsewhere: the classic read-by-setting (restored at once)
    os.umask(mask)
    return mask


def follow_umask(path: str | Path) -> None:
    """Give `path` (a file, or every file under a folder) the mode an ordinary write would have given it:
    0o666 minus the umask (plus any execute bits it had).

    safetensors >= 0.8 writes through a temporary file created 0600 and renamed into place, so a
    checkpoint (`model.safetensors`, the processors' state files) or projector saved into a shared root
    would be unreadable by the group even where the umask allows it; call this after such writes.
    Files this user does not own are left as they are.
    """
    path = Path(path)
    want = 0o666 & ~current_umask()
    for p in ([path] if path.is_file() else [q for q in path.rglob("*") if q.is_file()]):
        try:
            st = p.stat()
            mode = want | (st.st_mode & 0o111)
            if st.st_uid == os.getuid() and st.st_mode & 0o777 != mode:
                os.chmod(p, mode)
        except OSError:
            pass
