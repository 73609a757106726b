"""The policy's own loss on a (grafted) backbone: masked flow loss or token cross-entropy, and deterministic
prediction. (A fit's objective, what its projector is trained toward, is graftcache.fit.objectives'.)

lerobot's policies return the unreduced per-element loss from `model.forward`, so padded action steps
are masked here, once, the same way for both backbones.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Mapping
from typing import Any

import torch

from graftcache.backbones.batches import ACTION, ACTION_PAD, STATE


class PolicyLoss(ABC):
    """The loss half of a BackboneAdapter (mixed into it; uses its policy, chunking and device): what every
    policy loss shares (the start noise, the steps of prediction, the normalised chunk predicted, unnormalising) and
    the one member each must have, `loss`. Flow backbones take `FlowLoss`, pi0-FAST `TokenLoss`."""

    def sample_noise(self, batch_size: int, generator: torch.Generator | None = None) -> torch.Tensor:
        """Flow-matching start noise [B, chunk, max_action_dim] (on CPU from `generator`, then moved)."""
        noise = torch.randn(batch_size, self.chunk_size, self.max_action_dim, generator=generator)
        return noise.to(self.device)

    @abstractmethod
    def loss(self, batch: Mapping[str, Any], noise: torch.Tensor | None = None,
             time: torch.Tensor | None = None) -> torch.Tensor:
        """The training loss of a prepared batch: per sample [B] where `spec.loss_per_sample`, else a scalar."""

    @abstractmethod
    def _predict_chunk(self, batch: Mapping[str, Any], noise: torch.Tensor, num_steps: int) -> torch.Tensor:
        """The policy's `predict_action_chunk` with the given noise and number of denoising steps."""

    @property
    def num_steps(self) -> int:
        """Default number of denoising (or decoding) steps: the config field `spec.steps_field` names."""
        return getattr(self.config, self.spec.steps_field)

    def predict(self, batch: Mapping[str, Any], noise: torch.Tensor | None = None,
                num_steps: int | None = None) -> torch.Tensor:
        """Normalised action chunk [B, chunk, action_dim]; deterministic for a fixed `noise`."""
        batch = {k: v for k, v in batch.items() if k not in (ACTION, ACTION_PAD)}
        if noise is None:
            noise = self.sample_noise(batch[STATE].shape[0])
        was_training = self.policy.training
        try:
            return self._predict_chunk(batch, noise.to(self.device), num_steps or self.num_steps)
        finally:
            self.policy.train(was_training)

    def unnormalize(self, actions: torch.Tensor) -> torch.Tensor:
        """Normalised action chunk [..., action_dim] -> raw action units [..., action_dim], through lerobot's
        postprocessor (fed at the width it takes: `postprocessor_input`)."""
        return self.postprocessor(self.postprocessor_input(self.config, actions))


class FlowLoss(PolicyLoss):
    """Flow matching: the policy's own per-element flow loss, padded action steps masked here, once, the same way
    for every flow backbone. `time` is the noise level (1 = pure noise) whichever way the policy's own t runs
    (`spec.flow_time`)."""

    def sample_time(self, batch_size: int) -> torch.Tensor:
        """The policy's own time draw [B], as a noise level (the hook a backbone with another sampler overrides)."""
        return self.noise_level(self.policy.model.sample_time(batch_size, self.device))

    def noise_level(self, t: torch.Tensor) -> torch.Tensor:
        """The policy's own time `t` as graftcache's noise level (and back: the map is its own inverse)."""
        return t if self.spec.flow_time == "noise" else 1 - t

    @abstractmethod
    def _flow_losses(self, batch: Mapping[str, Any], noise: torch.Tensor, time: torch.Tensor) -> torch.Tensor:
        """lerobot's per-element flow-matching loss [B, chunk, max_action_dim] (no masking)."""

    def loss(self, batch: Mapping[str, Any], noise: torch.Tensor | None = None,
             time: torch.Tensor | None = None) -> torch.Tensor:
        """Per-sample flow loss [B]: mean over real action dims and the chunk steps that are not padding.

        `noise` [B, chunk, max_action_dim] and `time` [B] default to the model's own samplers (global RNG).
        """
        batch_size = batch[STATE].shape[0]
        noise = self.sample_noise(batch_size) if noise is None else noise
        time = self.sample_time(batch_size) if time is None else time
        losses = self._flow_losses(batch, noise, time)[:, :, : self.action_dim]
        pad = batch.get(ACTION_PAD)
        valid = torch.ones(losses.shape[:2], device=losses.device) if pad is None else (~pad.bool()).float()
        per_step = losses.mean(dim=2)
        return (per_step * valid).sum(dim=1) / valid.sum(dim=1).clamp(min=1.0)


class TokenLoss(PolicyLoss):
    """Cross-entropy on action tokens (pi0-FAST): no flow time, and lerobot's loss is one token-weighted mean over
    the batch (`spec.loss_per_sample` False: its cells never share a pass). Prediction decodes tokens; the noise a
    caller passes is ignored."""
