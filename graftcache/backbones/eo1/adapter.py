"""EO-1 (lerobot 0.6: Qwen2.5-VL-3B + a flow-matching action head in the same sequence) as a graftable backbone.

Vision path (processor_eo1.py, modeling_eo1.py; transformers qwen2_5_vl): the preprocessor turns every camera
into a chat message and Qwen's processor resizes each image (`smart_resize`: multiples of 28 between the
config's min and max pixels), cuts it into 14 px patches ordered by 2x2 merge block, and writes one
`<|image_pad|>` token per merged block into the prompt. In the model, `Qwen2_5_VLModel.get_image_features`
runs the ViT (`visual`: patch embedding, window-attention blocks) and its `merger` (RMSNorm, 2x2 concat, MLP
into the LM width) and scatters the tokens into the image-pad positions of the sequence, camera after camera.
So the tokens per camera are the merged grid of the processor's resize of the dataset's frame: LIBERO's 256 px
-> 252 px -> 18x18 patches -> 9x9 = 81 tokens with the released processor bounds.

Graft slots: those image-pad positions, every camera. The tower (`visual.blocks`) becomes the pass-through and
the merger (the connector) the projector; Qwen's `get_image_features` is shadowed on the instance so that,
grafted, it projects the cached features instead of running the ViT (unchanged otherwise). The prompt is the
policy's own, built from blank frames of the dataset's size (the prompt depends on the image size only, never
on the pixels), so the pad positions, M-RoPE positions and attention masks are exactly the policy's.

EO-1 draws its flow time and noise inside `forward` and `sample_actions`; `loss` and `predict` run lerobot's own
code with those two samplers shadowed to return the given draws, and `loss` reads the velocity from the action
head's output (lerobot reduces the loss to a scalar). The sampler needs every sample's action span at the same
position, which lerobot gets from left padding at inference: `predict` re-lays a right-padded (training) batch
to the left, token for token.
"""

from __future__ import annotations

import contextlib
import functools
import logging
from collections.abc import Iterable, Iterator, Mapping
from pathlib import Path
from typing import Any

import torch
from torch import nn
from transformers.modeling_outputs import BaseModelOutputWithPooling

from graftcache.backbones.base import BackboneAdapter, vlm_folder
from graftcache.backbones.batches import ACTION, STATE
from graftcache.backbones.eo1.spec import QWEN_STEP, SPEC
from graftcache.backbones.eo1.tiny import construct
from graftcache.backbones.given_draws import shadowed
from graftcache.backbones.patching import patched
from graftcache.backbones.policy_loss import FlowLoss
from graftcache.backbones.qwen_vl import (
    TowerReads,
    cached_token_count,
    check_slots,
    image_token_counts,
    merged_grid,
    projected_images,
    prompt_grid,
    tied_head_keys,
    vit_outputs,
)
from graftcache.backbones.tiny_assets import QWEN_VL_DIR
from graftcache.errors import BackboneError
from graftcache.graft import feature_key

SEQUENCE_KEYS = ("input_ids", "attention_mask", "mm_token_type_ids")


def left_padded(batch: Mapping[str, Any]) -> dict[str, Any]:
    """A right-padded prompt batch re-laid with its padding on the left (what lerobot's processor writes at
    inference): each right-padded row rolled right by its number of pad tokens."""
    out = dict(batch)
    mask = batch["attention_mask"]
    pads = torch.where(mask[:, -1] == 0, (mask == 0).sum(dim=1), 0).tolist()
    for key in SEQUENCE_KEYS:
        out[key] = torch.stack([row.roll(n) for row, n in zip(batch[key], pads)])
    return out


@contextlib.contextmanager
def processor_kwargs_quiet() -> Iterator[None]:
    """Mute transformers' per-call warning that lerobot's EO-1 step passes the pixel bounds to
    `apply_chat_template` as plain kwargs (transformers 5 still applies them: see the released-geometry test)."""
    logger = logging.getLogger("transformers.processing_utils")
    level = logger.level
    logger.setLevel(logging.ERROR)
    try:
        yield
    finally:
        logger.setLevel(level)


class EO1Adapter(TowerReads, FlowLoss, BackboneAdapter):
    name = "eo1"
    spec = SPEC

    def _patch_graft(self, graft) -> None:
        """Grafted, Qwen's `get_image_features` projects the cached features (undone by reset)."""
        graft.shadow(self.policy.model.vlm_backbone.model, "get_image_features", self._image_features)

    # ------------------------------------------------------------------------------ construction
    @classmethod
    def _construct(cls, config, marker: dict | None) -> nn.Module:
        """EO1Policy with its VLM built from the saved `vlm_config` (the checkpoint holds the weights): lerobot's
        constructor would otherwise first fetch `vlm_base`'s own weights. Built on the meta device, the LM head
        comes out untied from the word embedding: tied again, as transformers ties it, so the policy holds (and
        counts) that tensor once."""
        policy = construct(config)
        policy.model.vlm_backbone.tie_weights()
        return policy

    @classmethod
    def _checkpoint_keys(cls, policy: nn.Module, file_keys: Iterable[str]) -> dict[str, str]:
        """Qwen2.5-VL-3B ties its LM head to the word embedding; safetensors keeps one of the two names: read the
        other from it."""
        return tied_head_keys(file_keys, "model.vlm_backbone.lm_head.weight",
                              "model.vlm_backbone.model.language_model.embed_tokens.weight")

    @classmethod
    def _qwen_folder(cls, config, marker: dict | None) -> Path:
        """The Qwen2.5-VL processor folder `vlm_base` names (graftcache.backbones.base.vlm_folder)."""
        return vlm_folder(config.vlm_base, marker, QWEN_VL_DIR, "EO-1's Qwen2.5-VL processor")

    @classmethod
    def _processor_overrides(cls, config, marker: dict | None, device: str) -> tuple[dict, dict]:
        pre, post = super()._processor_overrides(config, marker, device)
        pre["eo1_qwen_processor"] = {"processor_name": str(cls._qwen_folder(config, marker))}
        return pre, post

    @classmethod
    def _make_processors(cls, config, stats: dict, marker: dict | None):
        from lerobot.policies.eo1.processor_eo1 import make_eo1_pre_post_processors

        config.vlm_base = str(cls._qwen_folder(config, marker))
        return make_eo1_pre_post_processors(config, dataset_stats=stats)

    # ------------------------------------------------------------------------------ geometry
    @property
    def _vision_owner(self) -> nn.Module:
        return self.policy.model.vlm_backbone.model.visual  # Qwen2_5_VisionTransformerPretrainedModel

    @classmethod
    def _grid_of_config(cls, config, marker: dict | None) -> tuple[int, int]:
        """The merged grid of the first camera's frame (the dataset's size, as the config declares it)."""
        cameras = list(config.image_features.values())
        if not cameras:
            raise BackboneError("eo1 config declares no camera")
        vision = config.vision_config
        return merged_grid(tuple(cameras[0].shape[-2:]), vision.patch_size, vision.spatial_merge_size,
                           config.image_min_pixels, config.image_max_pixels)

    # ------------------------------------------------------------------------------ images
    @functools.cached_property
    def _qwen_processor(self):
        steps = [s for s in self.preprocessor.steps if type(s).__name__ == QWEN_STEP]
        if not steps:
            raise BackboneError(f"{self.name}: the preprocessor has no {QWEN_STEP}")
        return steps[0]

    def _image_features(self, own, qwen: nn.Module, pixel_values: torch.Tensor, image_grid_thw=None, **kwargs):
        """Qwen's `get_image_features`, or grafted: the cached features [images x tokens, C] through the
        pass-through and the projector, split per image as Qwen splits them. The projector sees them a sample a
        row, [B, cameras x tokens, C]: a fused projector (graftcache.graft.FusedProjector) routes rows."""
        if not self.grafted:
            return own(qwen, pixel_values, image_grid_thw, **kwargs)
        tokens = projected_images(*self._tower_and_connector(), pixel_values, image_grid_thw,
                                  qwen.visual.spatial_merge_size, len(self.config.image_features))
        return BaseModelOutputWithPooling(last_hidden_state=pixel_values, pooler_output=tokens)

    def _vision(self, images: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """[B, 3, H, W] in [0, 1] through the policy's own processor and ViT: (pre-merger patch grid [B, gh, gw,
        C] in raster order, post-merger tokens [B, T, D])."""
        self._check_native(images)
        step = self._qwen_processor
        frames = images.clamp(0, 1).mul(255.0).round().to(torch.uint8).cpu()  # EO1ConversationTemplateStep
        inputs = step._processor.image_processor(images=list(frames), min_pixels=step.image_min_pixels,
                                                 max_pixels=step.image_max_pixels, return_tensors="pt")
        return vit_outputs(self._vision_owner, inputs["pixel_values"], inputs["image_grid_thw"])

    def _feature_images(self, batch: Mapping[str, Any], excluded_keys: set[str]) -> dict[str, Any]:
        """Grafted stand-in for EO1Policy._get_model_inputs: Qwen's `pixel_values` are the cached features of
        every image, sample after sample, camera after camera (the order of the image pads in the prompts)."""
        images, _ = super()._feature_images(batch)
        check_slots(self.name, {f.shape[1] for f in images},
                    set(image_token_counts(batch["image_grid_thw"], self._vision_owner.spatial_merge_size)))
        inputs = {k: v for k, v in batch.items()
                  if k not in excluded_keys and not k.startswith(feature_key(""))}
        inputs["pixel_values"] = torch.stack(images, dim=1).flatten(0, 2)
        return inputs

    def prepare(self, raw: Mapping[str, Any]) -> dict[str, Any]:
        """lerobot's preprocessor (prompt, padding, normalisation). Grafted, the prompt is made from blank frames
        whose processed grid is the cached features' (the token grid, or a pooling control's square grid; the
        processor's pixel bounds are set to that frame for the call), and the features ride along for
        `_feature_images`."""
        if not self.grafted:
            with processor_kwargs_quiet():
                return super().prepare(raw)
        batch = dict(raw)
        gh, gw = prompt_grid(self.name, "EO-1", self.token_grid, cached_token_count(self.name, batch, self.camera_keys))
        factor = self._vision_owner.config.patch_size * self._vision_owner.spatial_merge_size
        size = batch[STATE].shape[0]
        for key in self.config.image_features:
            batch[key] = torch.zeros(size, 3, gh * factor, gw * factor)
        step = self._qwen_processor
        pixels = gh * gw * factor * factor
        with patched(step, image_min_pixels=pixels, image_max_pixels=pixels), processor_kwargs_quiet():
            out = self.preprocessor(batch)
        for key in self.config.image_features:
            out.pop(key, None)
        return out

    # ----------------------------------------------------------------------------- policy loss
    def _flow_losses(self, batch: Mapping[str, Any], noise: torch.Tensor, time: torch.Tensor) -> torch.Tensor:
        """lerobot's EO-1 forward with the given draws; the per-element loss from the action head's velocity."""
        model = self.policy.model
        velocity = []
        hook = model.action_out_proj.register_forward_hook(lambda m, args, out: velocity.append(out))
        try:
            with shadowed(model, sample_noise=lambda shape, device: noise.to(device),
                          sample_time=lambda size, device: time.to(device)):
                self.policy.forward(dict(batch))
        finally:
            hook.remove()
        action = self.policy.prepare_action(batch[ACTION])
        u_t = noise.to(action.dtype) - action
        return (u_t - velocity[0].reshape(u_t.shape).to(u_t.dtype)) ** 2

    @torch.no_grad()
    def _predict_chunk(self, batch: Mapping[str, Any], noise: torch.Tensor, num_steps: int) -> torch.Tensor:
        """`EO1Policy.predict_action_chunk` from `noise` with `num_steps` Euler steps."""
        config, model = self.config, self.policy.model
        with patched(config, num_denoise_steps=int(num_steps)), \
                shadowed(model, sample_noise=lambda shape, device: noise.to(device)):
            return self.policy.predict_action_chunk(left_padded(batch))
