"""SmolVLA (lerobot 0.6, SmolVLM2-500M backbone) as a graftable backbone.

Vision path (modeling_smolvla.py:403, 625; smolvlm_with_expert.py:179-192): `prepare_images`
pads/resizes to 512 px and rescales to [-1, 1]; `embed_image` runs SigLIP-B/16 (32x32 patches x 768),
then the connector (pixel shuffle x4 -> Linear(12288 -> 960)) = 64 tokens x 960 per camera, which
`embed_prefix` multiplies by sqrt(960). The graft replaces SigLIP with a pass-through and the
connector with the projector; lerobot's sqrt(width) scaling still applies after it.

Attention: every LM and expert layer attends through the joint model's own `eager_attention_forward` (the VLM's
layers are never called as modules, so transformers' attention switch does not reach them); the fused path shadows
it on the instance with `_fused` (graftcache/backbones/attention.py).
"""

from __future__ import annotations

import contextlib
import functools
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import torch
from torch import nn

from graftcache.backbones.activation_checkpointing import WrappedActivationCheckpointing
from graftcache.backbones.attention import MASKED, fused_attention
from graftcache.backbones.base import BackboneAdapter, vlm_folder
from graftcache.backbones.batches import TOKEN_MASK, TOKENS
from graftcache.backbones.patching import Patches, patched
from graftcache.backbones.policy_loss import FlowLoss
from graftcache.backbones.smolvla.spec import SPEC
from graftcache.backbones.tiny_assets import SMOLVLM_DIR


class SmolVLAAdapter(WrappedActivationCheckpointing, FlowLoss, BackboneAdapter):
    name = "smolvla"
    spec = SPEC

    # ------------------------------------------------------------------------------ construction
    @classmethod
    def _construct(cls, config, marker: dict | None) -> nn.Module:
        from lerobot.policies.smolvla.modeling_smolvla import SmolVLAPolicy

        # The policy's safetensors hold every VLM weight: do not make lerobot load SmolVLM2's own
        # weights first (bf16, and they would have to be in the cache). Config + processor suffice.
        config.load_vlm_weights = False
        config.vlm_model_name = str(cls._vlm_folder(config, marker))
        return SmolVLAPolicy(config)

    @classmethod
    def _vlm_folder(cls, config, marker: dict | None) -> Path:
        """The SmolVLM config/processor folder `vlm_model_name` names (graftcache.backbones.base.vlm_folder)."""
        return vlm_folder(config.vlm_model_name, marker, SMOLVLM_DIR, "SmolVLA's VLM config/processor")

    @classmethod
    def _grid_of_config(cls, config, marker: dict | None) -> tuple[int, int]:
        from transformers import AutoConfig

        vlm = AutoConfig.from_pretrained(cls._vlm_folder(config, marker))
        side = vlm.vision_config.image_size // vlm.vision_config.patch_size // vlm.scale_factor
        return side, side

    @classmethod
    def _processor_overrides(cls, config, marker: dict | None, device: str) -> tuple[dict, dict]:
        pre, post = super()._processor_overrides(config, marker, device)
        if marker is not None:  # the saved tokenizer path points into the package that saved it
            from transformers import AutoTokenizer

            pre["tokenizer_processor"] = {"tokenizer": AutoTokenizer.from_pretrained(SMOLVLM_DIR)}
        return pre, post

    @classmethod
    def _make_processors(cls, config, stats: dict, marker: dict | None):
        from lerobot.policies.smolvla.processor_smolvla import make_smolvla_pre_post_processors

        return make_smolvla_pre_post_processors(config, dataset_stats=stats)

    # ------------------------------------------------------------------------------ geometry
    @property
    def _vision_owner(self) -> nn.Module:
        return self.policy.model.vlm_with_expert.get_vlm_model()

    # ----------------------------------------------------------------------------- policy loss
    def _flow_losses(self, batch: Mapping[str, Any], noise, time) -> torch.Tensor:
        policy = self.policy
        images, img_masks = policy.prepare_images(batch)
        return policy.model.forward(
            images, img_masks, batch[TOKENS], batch[TOKEN_MASK], policy.prepare_state(batch),
            policy.prepare_action(batch), noise, time,
        )

    def _predict_chunk(self, batch: Mapping[str, Any], noise: torch.Tensor, num_steps: int) -> torch.Tensor:
        with _num_steps(self.config, num_steps):
            return self.policy.predict_action_chunk(dict(batch), noise=noise)

    def _recompute_slots(self) -> Iterator[tuple[nn.Module, str]]:
        """The attention of every layer (one function of the joint model) and each LM and expert layer's MLP."""
        joint = self.policy.model.vlm_with_expert
        yield joint, "eager_attention_forward"
        yield from self._mlp_slots()

    def _mlp_slots(self) -> Iterator[tuple[nn.Module, str]]:
        """Each LM and expert layer's MLP."""
        joint = self.policy.model.vlm_with_expert
        for layers in (joint.get_vlm_model().text_model.layers, joint.lm_expert.layers):
            for layer in layers:
                yield layer.mlp, "forward"

    def _switch_attention(self, patches: Patches, mode: str) -> None:
        """sdpa (the one other path): `_fused` shadows the joint model's eager attention."""
        joint = self.policy.model.vlm_with_expert
        patches.set(joint, "eager_attention_forward", functools.partial(_fused, joint))


def _fused(joint: nn.Module, attention_mask: torch.Tensor, batch_size: int, head_dim: int, query: torch.Tensor,
           key: torch.Tensor, value: torch.Tensor) -> torch.Tensor:
    """lerobot's `SmolVLMWithExpertModel.eager_attention_forward` in one kernel: [B, L, heads, D] queries, [B, S,
    kv_heads, D] keys and values and a bool [B, L, S] mask (True: attend) in, [B, L, heads * D] out, in the values'
    dtype; scaled by head_dim ** -0.5, masked scores at a finite minimum, as eager's."""
    mask = torch.where(attention_mask[:, None], 0.0, MASKED)
    out = fused_attention(query.transpose(1, 2).to(value.dtype), key.transpose(1, 2), value.transpose(1, 2), mask,
                          head_dim**-0.5)
    return out.transpose(1, 2).reshape(batch_size, -1, joint.num_attention_heads * head_dim)



@contextlib.contextmanager
def _num_steps(config, steps: int):
    """SmolVLA's sampler reads `config.num_steps` (it takes no argument); set it for one call."""
    with patched(config, num_steps=steps):
        yield
