"""The exported cell as a lerobot policy: the base policy grafted exactly as its fit grafted it, fed the features the
cell's encoder computes from the camera frames (graftcache.export.features), acting on chunks as the base does.

lerobot builds it with `from_pretrained` (its factory, `lerobot-eval --policy.path`); it never reads a weights file of
its own: the base policy loads through its graftcache adapter (the same loading a fit does), and the cell's encoder is
rebuilt from the export's manifest, its numerics fingerprint recomputed (graftcache.export.features). The frames reach
it from the export's preprocessor (graftcache.export.processors) and become the cell's features only when a chunk is
predicted, not for every action popped from the queue; the base policy's own preprocessing runs here, through the
adapter's `prepare`, as offline scoring runs it.
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
from graftcache.errors import ExportError
from graftcache.export.configuration_graftcache import EXPORT_FORMAT, GraftcacheConfig
from graftcache.export.features import load_cell_features, read_manifest
from graftcache.fit.controls import get_control
from graftcache.runtime import autocast, resolve_dtype

PROJECTOR_FILE = "projector.safetensors"


class GraftcachePolicy(PreTrainedPolicy):
    """A base lerobot VLA with the cell's projector (and LoRA) grafted in and its encoder in front."""

    config_class = GraftcacheConfig
    name = "graftcache"

    def __init__(self, config: GraftcacheConfig, folder: str | Path | None = None, **kwargs: Any) -> None:
        super().__init__(config)
        folder = Path(folder or config.pretrained_path or "")
        if not (folder / "config.json").is_file():
            raise ExportError(f"{folder}: not a graftcache export folder (no config.json)")
        if config.export_format != EXPORT_FORMAT:
            raise ExportError(f"{folder}: an export of format {config.export_format}, written by another graftcache "
                              f"(this one reads {EXPORT_FORMAT}); export run {config.run_id} again")
        self.folder = folder
        device = str(config.device or "cpu")
        manifest = read_manifest(folder)
        control = get_control(config.control)
        adapter = get_backbone(config.backbone).load(config.base_policy, device=device)
        width = manifest.extras[control.extra][-1] if control.extra else int(manifest.encoder["width"])
        adapter.graft(control.projector(width, adapter.lm_width))
        if control.lora:
            adapter.add_lora(rank=config.lora_rank)
        if control.train:
            self._load_trained(adapter, folder / PROJECTOR_FILE)
        adapter.policy.eval()
        self.adapter = adapter
        self.features = load_cell_features(folder, json.loads((folder / "config.json").read_text()), device)
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
        """lerobot calls it at each episode's start: the queue empties, a dose cell's noise starts again."""
        self._queue.clear()
        self.features.reset()

    def forward(self, batch: dict[str, Tensor]) -> tuple[Tensor, dict | None]:
        raise ExportError("a graftcache export is evaluated, not trained: fit the cell with `graftcache fit`")

    @torch.no_grad()
    def predict_action_chunk(self, batch: dict[str, Tensor], noise: Tensor | None = None, **kwargs: Any) -> Tensor:
        """Normalised action chunk [B, chunk, action_dim] of a batch from the export's preprocessor (camera frames,
        raw state, task strings), the frames turned into the cell's features here; `noise` [B, chunk, max_action_dim]
        fixes the flow's start, as offline scoring fixes it per frame."""
        batch = self.features.observe(batch, self.config.cameras, str(self.folder))
        task = batch["task"]
        prepared = self.adapter.prepare({**batch, "task": [task] if isinstance(task, str) else list(task)})
        with autocast(self.adapter.device, self.dtype):
            return self.adapter.predict(prepared, noise=noise, num_steps=self.config.num_denoise_steps).float()

    @torch.no_grad()
    def select_action(self, batch: dict[str, Tensor], noise: Tensor | None = None, **kwargs: Any) -> Tensor:
        """The next normalised action [B, action_dim] (the export's postprocessor takes it at this width, whatever
        width the base policy's own emits): a chunk is predicted when the queue is empty (from `noise`, as
        `predict_action_chunk`) and its first `n_action_steps` run."""
        if not self._queue:
            chunk = self.predict_action_chunk(batch, noise=noise)[:, : self.config.n_action_steps]
            self._queue.extend(chunk.transpose(0, 1))
        return self._queue.popleft()
