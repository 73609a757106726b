"""Building the native vision towers the encoder catalog declares: `smolvla-native`, `pi05-native`.

The native controls need the released tower's own outputs in the cache, computed once like any
other encoder's: its pre-connector patch grid (pooled like every grid, for `native-graft`) and its
post-connector tokens (extra array `connector`, for `native` and as the `align` target). Both come
from the policy's own modules through the adapter (`native_patch_grid`, `native_tokens`), so the
pixels go through the policy's own image preparation (pad/resize, [-1, 1] rescale) and nothing of
the tower is re-implemented.

The spec is policy-specific (a released SmolVLA tower is SigLIP at 512 px with a 32x32x768 grid, a
tiny one is far smaller), so the builder returns an encoder whose spec is measured on the loaded
policy; the manifest records that spec and the policy's weights hash, and which of two facts about a tiny
policy's weights holds: trained by train-tiny (`weights.trained_by`, its training record beside the checkpoint) or
random-init (never trained: `random_init`). The catalog (stage 1) names
`build_tower_encoder` by import string, so this module is imported only when a native tower is built.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import torch
import torch.nn.functional as F

from graftcache.backbone_registry import backbone_of_native
from graftcache.backbones import get_backbone
from graftcache.backbones.tiny_record import read_record, trained_image_size
from graftcache.encoders import Encoder, EncoderSpec, LoadRequest, weights_info
from graftcache.errors import EncoderError


def policy_pixels(frames_u8: torch.Tensor, size: int) -> torch.Tensor:
    """uint8 frames [N, H, W, 3] -> uint8 [N, 3, size, size] (antialiased bilinear, rounded).

    Shared by native training (graftcache.pretrain) and the native-tower encoders, so a tower sees
    identically prepared pixels when it is trained and when its features are cached.
    """
    x = frames_u8.permute(0, 3, 1, 2).float()
    if tuple(x.shape[-2:]) != (size, size):
        x = F.interpolate(x, size=(size, size), mode="bilinear", antialias=True, align_corners=False)
    return x.round().clamp(0, 255).to(torch.uint8)


class TowerEncoder(Encoder):
    """A policy's vision tower: [0, 1] pixels -> pre-connector grid, plus post-connector tokens."""

    def __init__(self, spec: EncoderSpec, adapter, info: dict) -> None:
        super().__init__(spec, adapter.policy, info)
        self.adapter = adapter
        self.extra_shapes: dict[str, tuple[int, int]] = {}
        self.policy_cameras: tuple[str, ...] = adapter.cameras  # extract pairs the dataset's cameras with these

    def preprocess(self, frames_u8: torch.Tensor) -> torch.Tensor:
        """uint8 [B, H, W, 3] -> [0, 1] pixels [B, 3, S, S], exactly as native training prepared them;
        the policy's own image preparation runs inside the tower call."""
        super().preprocess(frames_u8[:1, :1, :1])  # the shared input validation
        return policy_pixels(frames_u8.to(self.device), self.spec.image_size).float().div_(255)

    def _grid(self, x: torch.Tensor) -> torch.Tensor:
        return self.adapter.native_patch_grid(x)

    @torch.no_grad()
    def forward_with_extras(self, x: torch.Tensor) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """(patch grid [B, gh, gw, C], {"connector": post-connector tokens [B, T, D]})."""
        with self._autocast():
            tokens = self.adapter.native_tokens(x)
        return self.forward_grid(x), {"connector": tokens.float()}


def build_tower_encoder(spec: EncoderSpec, req: LoadRequest) -> TowerEncoder:
    """Load the policy named by `--policy` and measure its tower's grid and connector shapes. The pixel
    size is the one a tiny checkpoint trained by train-tiny records, else the catalog's (released policies
    take the dataset's frames as they are)."""
    backbone = backbone_of_native(spec.name)
    if req.policy is None:
        raise EncoderError(f"encoder {spec.name!r} needs --policy (a hub id, a checkpoint folder, or the folder "
                           f"printed by `graftcache train-tiny --backbone {backbone}`)")
    if req.weights is not None or req.random_init:
        raise EncoderError(f"encoder {spec.name!r} takes its weights from --policy, not --weights/--random-init")
    adapter = get_backbone(backbone).load(req.policy, device=req.device)
    folder = Path(req.policy)
    size = (trained_image_size(folder) if folder.is_dir() else None) or spec.image_size
    probe = torch.zeros(1, 3, size, size)
    grid = adapter.native_patch_grid(probe)
    tokens = adapter.native_tokens(probe)
    measured = replace(spec, model_id=str(req.policy), image_size=size, grid=(grid.shape[1], grid.shape[2]),
                       width=grid.shape[3], pretrained_source=f"policy:{req.policy}")
    info = weights_info("policy", str(req.policy), adapter.policy_sha256)
    trained = folder.is_dir() and read_record(folder) is not None
    info["trained_by"] = "train-tiny" if trained else None
    info["random_init"] = adapter.random_init and not trained  # a tiny policy train-tiny never trained
    encoder = TowerEncoder(measured, adapter, info)
    encoder.extra_shapes = {"connector": (tokens.shape[1], tokens.shape[2])}
    return encoder
