"""What every tiny backbone shares: what one is built for (`TinyBuild`), the lerobot features and stats it is
built from, seeded construction, and the marker a tiny checkpoint folder carries so loading knows it is one.

Tiny policies are lerobot's own policy classes at small sizes, so every code path (processors, graft, loss,
sampling, save/load) is the real one; only the widths and depths shrink. Each backbone's tiny configuration lives in
its own folder (`graftcache/backbones/<name>/tiny.py`, `build_tiny`); the PaliGemma family's shared sizes in
graftcache/backbones/paligemma.py. A tiny checkpoint folder carries `graftcache_tiny.json` (the backbone and, for
the PaliGemma family whose sizes lerobot hard-codes, the geometry) so loading knows to build it at those sizes.
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from torch import nn

from graftcache.backbones.paligemma import Pi05TinyGeometry
from graftcache.errors import BackboneError

TINY_MARKER = "graftcache_tiny.json"


@dataclass(frozen=True)
class TinyBuild:
    """What one tiny policy is built for: the dataset's cameras and dims, plus chunking and the init seed. Not a
    spec (graftcache.backbones.spec.BackboneSpec, which never varies): each build may differ."""

    cameras: tuple[str, ...] = ("image", "image2")   # LIBERO: observation.images.image / image2
    state_dim: int = 8
    action_dim: int = 7
    chunk_size: int = 10
    num_steps: int = 4                                 # flow-matching denoising steps at inference
    seed: int = 0



def visual_features(tiny: TinyBuild, image_size: int) -> dict:
    """lerobot input features of a tiny policy: one square camera of `image_size` per camera of the build, and the
    state."""
    from lerobot.configs.types import FeatureType, PolicyFeature

    return {
        **{f"observation.images.{c}": PolicyFeature(FeatureType.VISUAL, (3, image_size, image_size))
           for c in tiny.cameras},
        "observation.state": PolicyFeature(FeatureType.STATE, (tiny.state_dim,)),
    }



def action_features(tiny: TinyBuild) -> dict:
    """lerobot output features of a tiny policy: the action of the build's width."""
    from lerobot.configs.types import FeatureType, PolicyFeature

    return {"action": PolicyFeature(FeatureType.ACTION, (tiny.action_dim,))}



def require_stats(stats: dict | None) -> dict:
    """The dataset stats a tiny policy's processors normalise with, refused in one line when absent."""
    if stats is None:
        raise BackboneError("policy 'tiny' has no stored normalisation: pass dataset_stats (state and action)")
    return stats



def seeded_policy(seed: int, construct: Callable[[], nn.Module]) -> nn.Module:
    """`construct()` with the global RNG seeded to `seed` (and restored after) and its prints muted: a tiny
    policy's weights depend on its build's seed only."""
    with torch.random.fork_rng(devices=[]), contextlib.redirect_stdout(io.StringIO()):
        torch.manual_seed(seed)
        return construct()



def build_seeded(tiny: TinyBuild, stats: dict | None, device: str, config,
                 construct: Callable[[Any], nn.Module], make_processors: Callable[..., tuple[Any, Any]]
                 ) -> tuple[nn.Module, Any, Any, None]:
    """A tiny build whose policy config holds its whole geometry (most backbones' `build_tiny`): the policy
    constructed from `config` at the build's seed (`seeded_policy`), lerobot's processor factory
    (`make_processors(config, dataset_stats=...)`) on the dataset's stats, the policy moved to `device`. No geometry
    for the marker: the saved config rebuilds the policy at its sizes."""
    policy = seeded_policy(tiny.seed, lambda: construct(config))
    pre, post = make_processors(config, dataset_stats=require_stats(stats))
    return policy.to(device), pre, post, None


def print_written(folder: Path) -> None:
    """What `python -m graftcache.backbones.<name>.tiny` prints once it has (re)written its shipped tiny folder: the
    folder and its files, to look over before committing them."""
    print(folder, sorted(p.name for p in folder.iterdir()))


def write_marker(folder: Path, backbone: str, geometry: Pi05TinyGeometry | None) -> None:
    payload = {"backbone": backbone, "geometry": dataclasses.asdict(geometry) if geometry else None}
    (folder / TINY_MARKER).write_text(json.dumps(payload, indent=1))


def read_marker(folder: Path) -> dict | None:
    """The tiny marker of a checkpoint folder, or None for a regular checkpoint."""
    path = folder / TINY_MARKER
    if not path.exists():
        return None
    try:
        payload = json.loads(path.read_text())
        geometry = payload.get("geometry")
        return {"backbone": payload["backbone"], "geometry": Pi05TinyGeometry(**geometry) if geometry else None}
    except (ValueError, KeyError, TypeError) as exc:
        raise BackboneError(f"{path}: unreadable tiny-backbone marker ({exc})") from None

