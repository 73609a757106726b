"""SmolVLA (lerobot 0.6, SmolVLM2-500M backbone) as a graftable backbone.

Vision path (modeling_smolvla.py:403, 625; smolvlm_with_expert.py:179-192): `prepare_images`
pads/resizes to 512 px and rescales to [-1, 1]; `embed_image` runs SigLIP-B/16 (32x32 patches x 768),
then the connector (pixel shuffle x4 -> Linear(12288 -> 960)) = 64 tokens x 960 per camera, which
`embed_prefix` multiplies by sqrt(960). The graft replaces SigLIP with a pass-through and the
connector with the projector; lerobot's sqrt(width) scaling still applies after it.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import torch
from torch import nn

from graftcache.backbones.activation_checkpointing import WrappedActivationCheckpointing
from graftcache.backbones.base import BackboneAdapter
from graftcache.backbones.batches import TOKEN_MASK, TOKENS
from graftcache.backbones.checkpoint import cached_repo
from graftcache.backbones.objectives import FlowObjective
from graftcache.backbones.patching import patched
from graftcache.backbones.spec import BackboneSpec
from graftcache.backbones.tiny_assets import SMOLVLM_DIR


class SmolVLAAdapter(WrappedActivationCheckpointing, FlowObjective, BackboneAdapter):
    name = "smolvla"
    spec = BackboneSpec(
        label="SmolVLA",
        lerobot_extra="smolvla",
        released_params=450_000_000,
        image_method="prepare_images",
        vision_slots=("vision_model", "connector"),
        lm_width="_vision_owner.config.text_config.hidden_size",
        module_paths={
            "language model": ("_vision_owner.text_model",),
            "action expert": ("policy.model.vlm_with_expert.lm_expert",),
            "state projection": ("policy.model.state_proj",),
            "action/time projections": tuple(f"policy.model.{m}" for m in (
                "action_in_proj", "action_out_proj", "action_time_mlp_in", "action_time_mlp_out")),
        },
        steps_field="num_steps",
        token_steps=("NewLineTaskProcessorStep", "TokenizerProcessorStep"),
        scaled_embeddings=True,
        cells_per_pass={"cpu": 1, "cuda": 4},
        activation_checkpointing=True,
        compiled_forward="policy.model",
    )

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
        """The SmolVLM config/processor folder the policy is built from (the shipped tiny one, a local
        folder, or the hub id's snapshot in the local HF cache)."""
        if marker is not None:
            return SMOLVLM_DIR
        if Path(config.vlm_model_name).is_dir():
            return Path(config.vlm_model_name)
        return cached_repo(config.vlm_model_name, "SmolVLA's VLM config/processor")

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

    # ------------------------------------------------------------------------------ objectives
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

    def _activation_checkpointing_slots(self) -> Iterator[tuple[nn.Module, str]]:
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



@contextlib.contextmanager
def _num_steps(config, steps: int):
    """SmolVLA's sampler reads `config.num_steps` (it takes no argument); set it for one call."""
    with patched(config, num_steps=steps):
        yield
