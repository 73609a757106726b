"""Tiny checkpoints trained by train-tiny: where they live, the record beside their weights, finding them again.

`graftcache train-tiny` (graftcache.pretrain) writes a checkpoint folder keyed by the dataset's identity and
the training recipe, with RECORD_FILE beside the weights; `--policy tiny` (fit, extract) finds it again
from the dataset, and the native tower reads the pixel size it was trained on. This module is the only one
that knows the record's name and fields.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from graftcache.errors import BackboneError
from graftcache.hashing import sha256_json
from graftcache.requests import DEFAULT_TINY_TRAIN, TinyTrainConfig

POLICIES_DIR = "policies"
RECORD_FILE = "graftcache_pretrain.json"


def policy_dir(root: Path, backbone: str, identity: dict, cfg: TinyTrainConfig) -> Path:
    """Folder of a tiny backbone trained by train-tiny, keyed by dataset content and training recipe."""
    digest = sha256_json({"fp": identity, "cfg": cfg.as_dict(backbone)})
    return root / POLICIES_DIR / f"tiny-{backbone}-{digest[:12]}"


def write_record(folder: Path, record: dict[str, Any]) -> None:
    (folder / RECORD_FILE).write_text(json.dumps(record, indent=2))


def read_record(folder: Path) -> dict[str, Any] | None:
    """The training record of a checkpoint folder; None where there is none or it cannot be read."""
    try:
        return json.loads((folder / RECORD_FILE).read_text())
    except (OSError, ValueError):
        return None


def trained_image_size(folder: Path) -> int | None:
    """The pixel size a tower trained by train-tiny was trained on (None: not a graftcache-trained checkpoint)."""
    record = read_record(folder)
    return int(record["config"]["image_size"]) if record else None


def tiny_policies(root: Path, backbone: str, identity: dict) -> list[tuple[Path, dict]]:
    """Tiny checkpoints trained by train-tiny of `backbone` for the dataset with `identity`, with their records."""
    found = []
    for folder in sorted((root / POLICIES_DIR).glob(f"tiny-{backbone}-*")):
        record = read_record(folder)
        if (folder / "config.json").is_file() and record is not None and record.get("backbone") == backbone \
                and record.get("dataset_identity") == identity:
            found.append((folder, record))
    return found


def resolve_policy(backbone: str, policy: str, identity: dict, root: Path, dataset_name: str = "DATASET") -> str:
    """`tiny` -> the tiny checkpoint trained by train-tiny for the dataset with `identity`; else as given.

    With several tiny checkpoints for the dataset (other steps or seeds), the one trained with the default
    recipe wins (at whichever compute dtype this machine resolved); otherwise the user must pick a folder.
    """
    if policy != "tiny":
        return policy
    found = tiny_policies(root, backbone, identity)
    if not found:
        raise BackboneError(f"no tiny {backbone} trained by train-tiny for dataset {dataset_name} in "
                            f"{root / POLICIES_DIR}; run: graftcache train-tiny --backbone {backbone} "
                            f"--dataset {dataset_name}")
    if len(found) > 1:
        def recipe(config: dict) -> dict:  # the compute dtype is resolved per machine, not part of the recipe
            return {k: v for k, v in config.items() if k != "compute_dtype"}

        default = recipe(DEFAULT_TINY_TRAIN.as_dict(backbone))
        found = [(f, r) for f, r in found if recipe(r.get("config", {})) == default] or found
    if len(found) > 1:
        raise BackboneError(f"several tiny {backbone} checkpoints for dataset {dataset_name}: "
                            f"{', '.join(str(f) for f, _ in found)}; pass one folder as --policy")
    return str(found[0][0])
