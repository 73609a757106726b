"""Turn what the user typed (a folder or a hub repo id) into a local dataset folder.

Nothing is downloaded: graftcache reads what lerobot (`$HF_LEROBOT_HOME/<repo_id>`) or
`hf download` (`$HF_HUB_CACHE/datasets--ORG--NAME/snapshots/<rev>`) already put on disk. Environment
variables are read at call time (not import time) so tests and CLIs can redirect them.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path

from graftcache.errors import DatasetError
from graftcache.hub_cache import hf_home
from graftcache.hub_cache import repo_dir as hub_repo_dir

_REPO_ID = re.compile(r"^[A-Za-z0-9][\w.-]*/[\w.-]+(@[\w.-]+)?$")
_HUB_DIR = re.compile(r"^datasets--(?P<org>.+?)--(?P<name>.+)$")


@dataclass(frozen=True)
class ResolvedSource:
    """A local dataset folder and, when it came from a hub cache, the repo id and snapshot revision."""

    root: Path
    repo_id: str | None
    revision: str | None


def lerobot_home() -> Path:
    """`$HF_LEROBOT_HOME`, else `<hf_home>/lerobot` (lerobot's rule)."""
    return Path(os.getenv("HF_LEROBOT_HOME") or hf_home() / "lerobot").expanduser()


def resolve_source(source: str | Path) -> ResolvedSource:
    """A folder path wins; otherwise `ORG/NAME[@REV]` is looked up in the lerobot home, then the hub cache."""
    path = Path(source).expanduser()
    if path.is_dir():
        return _from_folder(path.resolve())
    text = str(source)
    if not _REPO_ID.match(text):
        raise DatasetError(f"{text}: no such dataset folder (and not a hub repo id ORG/NAME)")
    repo_id, _, rev = text.partition("@")
    looked: list[str] = []
    if not rev:
        local = lerobot_home() / repo_id
        looked.append(str(local))
        if local.is_dir():
            return ResolvedSource(local, repo_id, None)
    repo_dir = hub_repo_dir(repo_id, "datasets")
    looked.append(str(repo_dir))
    if repo_dir.is_dir():
        revision = _pick_revision(repo_dir, rev or "main")
        return ResolvedSource(repo_dir / "snapshots" / revision, repo_id, revision)
    raise DatasetError(f"dataset {text!r} is not a folder and is not in the local caches "
                       f"(looked in {' and '.join(looked)}); nothing is downloaded")


def _pick_revision(repo_dir: Path, rev: str) -> str:
    """A branch/tag name via refs/<rev>, or a snapshot hash given directly."""
    ref = repo_dir / "refs" / rev
    if ref.is_file():
        revision = ref.read_text().strip()
    elif (repo_dir / "snapshots" / rev).is_dir():
        revision = rev
    else:
        snaps = sorted(p.name for p in (repo_dir / "snapshots").glob("*")) if (repo_dir / "snapshots").is_dir() else []
        raise DatasetError(f"{repo_dir}: no refs/{rev} and no snapshot {rev!r} "
                           f"(snapshots: {', '.join(snaps) or 'none'})")
    if not (repo_dir / "snapshots" / revision).is_dir():
        raise DatasetError(f"{ref}: points at snapshot {revision} which is missing under {repo_dir / 'snapshots'}")
    return revision


def _from_folder(path: Path) -> ResolvedSource:
    """A folder given by path; a hub snapshot folder still reports its repo id and revision."""
    parts = path.parts
    if len(parts) >= 3 and parts[-2] == "snapshots" and (m := _HUB_DIR.match(parts[-3])):
        return ResolvedSource(path, f"{m['org']}/{m['name']}", parts[-1])
    return ResolvedSource(path, None, None)
