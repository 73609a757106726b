"""The exported cell as a lerobot policy: the base policy grafted exactly as its fit grafted it, fed the features the
cell's encoder computes from the camera frames (graftcache.export.features), acting on chunks as the base does.

lerobot builds it with `from_pretrained` (its factory, `lerobot-eval --policy.path`); it never reads a weights file of
its own: the base policy loads through its graftcache adapter (the same loading a fit does), the encoder is rebuilt
from the cache's manifest, and the numerics fingerprint is recomputed here, refusing a drifted environment as `fit`
does. The saved processors are the base policy's own (normalisation stats, tokenizer).
"""

from __future__ import annotations

import json
from collections import deque
from pathlib import Path
from typing import Any

import torch
from lerobot.policies.pretrained import PreTrainedPolicy
from safetensors.torch import load_file
from torch import Tensor

from graftcache.backbones import get_backbone
from graftcache.encoders.fingerprint import compare, encoder_of, fingerprint
from graftcache.errors import ExportError
from graftcache.export.configuration_graftcache import GraftcacheConfig
from graftcache.export.features import CellFeatures
from graftcache.fit.controls import get_control
from graftcache.fit.controls import zero as zero_features
from graftcache.graft import feature_key
from graftcache.runtime import autocast, resolve_dtype
from graftcache.store import Manifest

MANIFEST_FILE = "manifest.json"
PROJECTOR_FILE = "projector.safetensors"
IMAGE_PREFIX = "observation.images."


def read_manifest(folder: Path) -> Manifest:
    """The cache manifest an export carries (how to rebuild its encoder, its numerics fingerprint)."""
    path = folder / MANIFEST_FILE
    try:
        raw = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise ExportError(f"{path}: cannot read the cache manifest of this export ({e})") from None
    return Manifest.read(raw["manifest"], str(path), raw["key"])


class GraftcachePolicy(PreTrainedPolicy):
    """A base lerobot VLA with the cell's projector (and LoRA) grafted in and its encoder in front."""

    config_class = GraftcacheConfig
    name = "graftcache"

    def __init__(self, config: GraftcacheConfig, folder: str | Path | None = None, **kwargs: Any) -> None:
        super().__init__(config)
        folder = Path(folder or config.pretrained_path or "")
        if not (folder / "config.json").is_file():
            raise ExportError(f"{folder}: not a graftcache export folder (no config.json)")
        self.folder = folder
        device = str(config.device or "cpu")
        manifest = read_manifest(folder)
        control = get_control(config.control)
        encoder = encoder_of(manifest, device)
        self._check_numerics(manifest, encoder, device)
        self.features = CellFeatures(encoder, manifest, config.pool_grid, extra=control.extra,
                                     zero=control.transform is zero_features)
        adapter = get_backbone(config.backbone).load(config.base_policy, device=device)
        width = manifest.extras[control.extra][-1] if control.extra else int(manifest.encoder["width"])
        adapter.graft(control.projector(width, adapter.lm_width))
        if control.lora:
            adapter.add_lora(rank=config.lora_rank)
        if control.train:
            self._load_trained(adapter, folder / PROJECTOR_FILE)
        adapter.policy.eval()
        self.adapter = adapter
        self.dtype = resolve_dtype(config.compute_dtype)
        self._queue: deque[Tensor] = deque()

    @classmethod
    def from_pretrained(cls, pretrained_name_or_path: str | Path, *, config: GraftcacheConfig | None = None,
                        **kwargs: Any) -> GraftcachePolicy:
        """lerobot's factory entry: the export folder's cell, rebuilt (no weights file of its own to read)."""
        folder = Path(pretrained_name_or_path)
        config = config or GraftcacheConfig.from_pretrained(folder)
        policy = cls(config, folder)
        policy.eval()
        return policy

    def _check_numerics(self, manifest: Manifest, encoder, device: str) -> None:
        """The cache's numerics fingerprint recomputed here: an environment whose encoder computes other features
        than the ones the cell was scored on is refused in one line (`accept_numerics_drift` lets it run)."""
        cfg = self.config
        if encoder.weights_info.get("sha256") != manifest.weights_sha256:
            raise ExportError(f"{self.folder}: the {manifest.encoder_name} weights found here are not those of cache "
                              f"{cfg.cache_key}")
        recorded = manifest.numerics
        check = compare(cfg.cache_key, recorded, fingerprint(encoder, recorded["compute_dtype"], device),
                        manifest.versions)
        if check.status == "drift" and not cfg.accept_numerics_drift:
            raise ExportError(f"{self.folder}: {check.line()}; refused (--policy.accept_numerics_drift=true runs it)")

    def _load_trained(self, adapter, path: Path) -> None:
        """The cell's trained parameters (projector, LoRA), by the names its fit saved them under."""
        if not path.is_file():
            raise ExportError(f"{path}: missing; this export's control trains a projector")
        saved = load_file(str(path), device=str(adapter.device))
        params = dict(adapter.policy.named_parameters())
        unknown = sorted(set(saved) - set(params))
        missing = sorted(n for n, p in params.items() if p.requires_grad and n not in saved)
        if unknown or missing:
            raise ExportError(f"{path}: does not fit {self.config.backbone} grafted for control {self.config.control} "
                              f"({'unknown ' + unknown[0] if unknown else 'missing ' + missing[0]})")
        with torch.no_grad():
            for n, t in saved.items():
                params[n].copy_(t)

    # ------------------------------------------------------------------------------ lerobot's policy interface
    def get_optim_params(self) -> dict:
        return {}

    def reset(self) -> None:
        self._queue.clear()

    def forward(self, batch: dict[str, Tensor]) -> tuple[Tensor, dict | None]:
        raise ExportError("a graftcache export is evaluated, not trained: fit the cell with `graftcache fit`")

    @torch.no_grad()
    def predict_action_chunk(self, batch: dict[str, Tensor], noise: Tensor | None = None, **kwargs: Any) -> Tensor:
        """Normalised action chunk [B, chunk, action_dim] of a preprocessed batch (the base policy's processors);
        `noise` [B, chunk, max_action_dim] fixes the flow's start, as offline scoring fixes it per frame."""
        fed = {k: v for k, v in batch.items() if not k.startswith(IMAGE_PREFIX)}
        for policy_camera, camera in self.config.cameras.items():
            key = IMAGE_PREFIX + camera
            if key not in batch:
                raise ExportError(f"{self.folder}: the observation has no {key} (feeds policy camera "
                                  f"{policy_camera}); pass lerobot-eval a --rename_map that provides it")
            fed[feature_key(IMAGE_PREFIX + policy_camera)] = self.features(batch[key].to(self.adapter.device))
        with autocast(self.adapter.device, self.dtype):
            return self.adapter.predict(fed, noise=noise, num_steps=self.config.num_denoise_steps).float()

    @torch.no_grad()
    def select_action(self, batch: dict[str, Tensor], **kwargs: Any) -> Tensor:
        """The next action: a chunk is predicted when the queue is empty and its first `n_action_steps` run."""
        if not self._queue:
            chunk = self.predict_action_chunk(batch)[:, : self.config.n_action_steps]
            self._queue.extend(chunk.transpose(0, 1))
        return self._queue.popleft()
