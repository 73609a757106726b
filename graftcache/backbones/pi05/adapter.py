"""pi0.5 (lerobot 0.6, PaliGemma gemma_2b + gemma_300m expert) as a graftable backbone.

Vision path (modeling_pi05.py:952, 483, 284): `_preprocess_images` pads/resizes to 224 px and
rescales to [-1, 1]; `embed_image` = PaliGemma `get_image_features(...).pooler_output`: SigLIP
So400m/14 (16x16 patches x 1152) -> multi_modal_projector Linear(1152 -> 2048) = 256 tokens x 2048
per camera, no further scaling. lerobot 0.6 carries its own adaRMS Gemma (policies/pi_gemma.py), so
pi0.5 runs on stock transformers. The graft replaces SigLIP with a pass-through and the projector
with the graft projector.

The prompt embeds the state discretised into 256 bins ("Task: ..., State: ...;\\nAction: "), so
tokens are made per batch by lerobot's preprocessor, not once per task.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Mapping
from typing import Any

import torch
from torch import nn

from graftcache.backbones.base import BackboneAdapter
from graftcache.backbones.batches import TOKEN_MASK, TOKENS
from graftcache.backbones.checkpoint import cached_repo
from graftcache.backbones.lean_load import openpi_keys
from graftcache.backbones.paligemma import GEMMA_ATTENTIONS, paligemma_tiny_tokenizer, pi05_processors, pi05_tiny_sizes
from graftcache.backbones.patching import Patches
from graftcache.backbones.pi05.spec import SPEC
from graftcache.backbones.policy_loss import FlowLoss

PALIGEMMA_TOKENIZER = "google/paligemma-3b-pt-224"  # hard-coded by processor_pi05.py:145


class PaliGemmaAdapter(BackboneAdapter):
    """What the PaliGemma policies (pi0.5, pi0, pi0-FAST) share: openpi's checkpoint keys, the PaliGemma tokenizer, the
    tower and its grid; each adds its construction, processors and policy loss."""

    # ------------------------------------------------------------------------------ construction
    @classmethod
    def _checkpoint_keys(cls, policy: nn.Module, file_keys: Iterable[str]) -> dict[str, str]:
        """As the policies' from_pretrained rename: openpi key fixes, then a "model." prefix."""
        return openpi_keys(policy, file_keys)

    @classmethod
    def _tokenizer(cls, marker: dict | None):
        if marker is not None:
            return paligemma_tiny_tokenizer()
        from transformers import AutoTokenizer

        return AutoTokenizer.from_pretrained(cached_repo(PALIGEMMA_TOKENIZER, "pi0.5's tokenizer"))

    @classmethod
    def _processor_overrides(cls, config, marker: dict | None, device: str) -> tuple[dict, dict]:
        pre, post = super()._processor_overrides(config, marker, device)
        pre["tokenizer_processor"] = {"tokenizer": cls._tokenizer(marker)}
        return pre, post

    # ------------------------------------------------------------------------------ geometry
    @property
    def _vision_owner(self) -> nn.Module:
        return self.policy.model.paligemma_with_expert.paligemma.model  # PaliGemmaModel

    def _mlp_slots(self) -> Iterator[tuple[nn.Module, str]]:
        """Each language-model layer's MLP (lerobot and transformers call `layer.mlp(...)`)."""
        for layer in self._vision_owner.language_model.layers:
            yield layer.mlp, "forward"

    @classmethod
    def _grid_of_config(cls, config, marker: dict | None) -> tuple[int, int]:
        if marker is not None:
            patch = marker["geometry"].patch_size
        else:  # lerobot builds PaliGemma's default vision config (So400m/14) and changes only the image size
            from transformers.models.auto import CONFIG_MAPPING

            patch = CONFIG_MAPPING["paligemma"]().vision_config.patch_size
        side = config.image_resolution[0] // patch
        return side, side

    # ------------------------------------------------------------------------------ attention
    def _switch_attention(self, patches: Patches, mode: str) -> None:
        GEMMA_ATTENTIONS[mode](patches, self.policy)


class PI05Adapter(FlowLoss, PaliGemmaAdapter):
    name = "pi05"
    spec = SPEC

    # ------------------------------------------------------------------------------ construction
    @classmethod
    def _construct(cls, config, marker: dict | None) -> nn.Module:
        from lerobot.policies.pi05.modeling_pi05 import PI05Policy

        if marker is None:
            return PI05Policy(config)
        with pi05_tiny_sizes(marker["geometry"]):
            return PI05Policy(config)

    @classmethod
    def _make_processors(cls, config, stats: dict, marker: dict | None):
        return pi05_processors(config, stats, cls._tokenizer(marker))


    # ----------------------------------------------------------------------------- policy loss
    def _flow_losses(self, batch: Mapping[str, Any], noise, time) -> torch.Tensor:
        policy = self.policy
        images, img_masks = policy._preprocess_images(batch)
        return policy.model.forward(
            images, img_masks, batch[TOKENS], batch[TOKEN_MASK], policy.prepare_action(batch), noise, time
        )

    def _predict_chunk(self, batch: Mapping[str, Any], noise: torch.Tensor, num_steps: int) -> torch.Tensor:
        return self.policy.predict_action_chunk(dict(batch), noise=noise, num_steps=num_steps)

    def _mlp_slots(self) -> Iterator[tuple[nn.Module, str]]:
        """The language model's MLPs and the action expert's (compute_layer_complete calls `layer.mlp(...)`)."""
        yield from super()._mlp_slots()
        for layer in self.policy.model.paligemma_with_expert.gemma_expert.model.layers:
            yield layer.mlp, "forward"

    def _switch_recompute(self, on: bool) -> None:
        """lerobot's own switch (every LM and expert layer, in training mode)."""
        if on:
            self.policy.model.gradient_checkpointing_enable()
        else:
            self.policy.model.gradient_checkpointing_disable()
