"""EVO1 (lerobot 0.6: InternVL3-1B cut to 14 LM layers + a cross-attending flow-matching action head) as a
graftable backbone.

Vision path (modeling_evo1.py, internvl3_embedder.py; transformers internvl): the policy hands each camera's
[0, 1] frames to its `InternVL3Embedder`, which resizes them to the tower's size (448 px released, bicubic),
ImageNet-normalises them, pads the views to `max_views` with zero images (masked out of attention) and writes a
prompt "Image-i: <img><IMG_CONTEXT> x image_seq_length</img>" per view before the task. In the model,
`InternVLModel.get_image_features` runs InternViT, drops its CLS token, pixel-shuffles the 32x32 patch grid
to 16x16 (4x the width) and projects it with `multi_modal_projector` (LayerNorm, Linear, GELU, Linear) into the
LM width; those 256 tokens per view are scattered into the `<IMG_CONTEXT>` positions. The LM's last hidden
states (all valid tokens) are the action head's cross-attention context.

Graft slots: the `<IMG_CONTEXT>` positions of every real camera. The tower (`vision_tower`) becomes the
pass-through and the projector (`multi_modal_projector`, after the pixel shuffle) the graft projector; the
native tokens cached for the `native` control are that projector's output. Grafted, the embedder's pixel step
(resize, normalise) is bypassed: the cached features of each camera, with zero features for the padded views,
go straight to `get_image_features`, which is shadowed on the instance to project them instead of running
InternViT and the shuffle; the prompt carries as many `<IMG_CONTEXT>` per view as the features have tokens (the
token grid 16x16 or a pooling control's grid: InternVL's LM positions are 1-D, so any count fits). EVO1 embeds
without gradients unless its config finetunes the VLM (stage 2): grafted, its `_compute_fused_tokens` is
replaced by the same call with gradients, so the projector (and LoRA) train whatever the checkpoint's stage.

EVO1's head draws its own flow time (Beta(2, 2) clamped to [0.02, 0.98]) and noise (uniform in [-1, 1]) inside
`forward` / `get_action`, with the flow running from noise at t = 0 to the action at t = 1. `loss` and
`predict` therefore run the head's own modules (`_prepare_context`, `_project_actions`, its blocks, pooling and
MLP) with the given draws: graftcache's `time` is the noise level (1 at pure noise, as for pi0), EVO1's t is
1 - time; graftcache's noise is standard normal for every backbone (training draws and the scorer's fixed
per-frame draws), mapped here onto EVO1's uniform through the normal CDF (`_uniform`).
tests/backbones/test_evo1.py checks both against lerobot's `forward` and `predict_action_chunk` under the same
random draws.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch
from torch import nn
from transformers.modeling_outputs import BaseModelOutputWithPooling

from graftcache.backbones.base import BackboneAdapter, is_empty_camera, vlm_folder
from graftcache.backbones.batches import ACTION
from graftcache.backbones.evo1.spec import SPEC
from graftcache.backbones.evo1.tiny import INTERNVL_DIR, construct
from graftcache.backbones.patching import patched
from graftcache.backbones.policy_loss import FlowLoss
from graftcache.errors import BackboneError


def token_grid(image_size: int, vision, downsample_ratio: float) -> tuple[int, int]:
    """Tokens per camera as a grid: the tower's patch grid at `image_size`, pixel-shuffled by `downsample_ratio`."""
    patch = vision.patch_size[0] if isinstance(vision.patch_size, (list, tuple)) else vision.patch_size
    side = int(image_size // patch * downsample_ratio)
    return side, side


class Evo1Adapter(FlowLoss, BackboneAdapter):
    name = "evo1"
    spec = SPEC

    def _patch_graft(self, graft) -> None:
        """Grafted, the embedder takes the cached features, InternVL's `get_image_features` projects them, and images
        are embedded with gradients (see the module docstring; undone by reset)."""
        embedder, internvl = self.policy.model.embedder, self._vision_owner
        graft.patches.set(embedder, "get_fused_image_text_embedding_batched", functools.partial(
            self._fused_embedding, embedder.get_fused_image_text_embedding_batched))
        graft.patches.set(internvl, "get_image_features",
                          functools.partial(self._image_features, internvl.get_image_features))
        graft.override("_compute_fused_tokens", self._fused_tokens)

    # ------------------------------------------------------------------------------ construction
    @classmethod
    def _internvl_folder(cls, config, marker: dict | None) -> Path:
        """The InternVL config and tokenizer folder `vlm_model_name` names (graftcache.backbones.base.vlm_folder)."""
        return vlm_folder(config.vlm_model_name, marker, INTERNVL_DIR, "EVO1's InternVL config and tokenizer")

    @classmethod
    def _configure(cls, folder: Path, config, marker: dict | None) -> None:
        config.vlm_model_name = str(cls._internvl_folder(config, marker))

    @classmethod
    def _construct(cls, config, marker: dict | None) -> nn.Module:
        """Evo1Policy with its InternVL built from `vlm_model_name`'s config (the checkpoint holds the weights):
        lerobot's embedder would otherwise first load the base VLM's weights."""
        return construct(config)

    @classmethod
    def _make_processors(cls, config, stats: dict, marker: dict | None):
        from lerobot.policies.evo1.processor_evo1 import make_evo1_pre_post_processors

        return make_evo1_pre_post_processors(config, dataset_stats=stats)

    # ------------------------------------------------------------------------------ geometry
    @property
    def _vision_owner(self) -> nn.Module:
        return self.policy.model.embedder.model  # transformers InternVLModel

    @classmethod
    def _grid_of_config(cls, config, marker: dict | None) -> tuple[int, int]:
        """The pixel-shuffled grid of the tower at `image_resolution` (every frame is resized to it)."""
        from transformers import AutoConfig

        internvl = AutoConfig.from_pretrained(cls._internvl_folder(config, marker))
        return token_grid(int(config.image_resolution[0]), internvl.vision_config, internvl.downsample_ratio)

    # ------------------------------------------------------------------------------ images
    def _fused_tokens(self, prompts: list[str], images: list[torch.Tensor], masks: torch.Tensor):
        """Evo1Policy._compute_fused_tokens with gradients to the graft: the LM's context tokens and mask."""
        policy = self.policy
        fused, context = policy.model.get_vl_embeddings(images=images, image_mask=masks, prompt=prompts,
                                                        return_cls_only=self.config.return_cls_only)
        fused = fused.to(device=policy._device, dtype=policy._compute_dtype)
        return fused, None if context is None else context.to(policy._device)

    def _feature_images(self, batch: Mapping[str, Any]) -> tuple[list[torch.Tensor], torch.Tensor]:
        """Grafted stand-in for Evo1Policy._collect_image_batches: the real cameras' cached features [B, T, C]
        and the view mask [B, max_views] (real cameras first, as lerobot marks the views present)."""
        images, _ = super()._feature_images(batch)
        real = [f for key, f in zip(self.config.image_features, images) if not is_empty_camera(key)]
        masks = torch.zeros(real[0].shape[0], self.config.max_views, dtype=torch.bool, device=real[0].device)
        masks[:, :len(real)] = True
        return real, masks

    def _fused_embedding(self, own, camera_images, image_masks, text_prompts, return_cls_only=True):
        """The embedder's batched embedding; grafted, the cached features stand in for the resized pixels: one
        [T, C] "image" per view (zeros for the padded views), with T `<IMG_CONTEXT>` slots per view."""
        if not self.grafted:
            return own(camera_images, image_masks, text_prompts, return_cls_only)
        counts = {f.shape[1] for f in camera_images}
        if len(counts) != 1:
            raise BackboneError(f"{self.name}: cameras carry different token counts ({sorted(counts)})")
        embedder, views = self.policy.model.embedder, int(image_masks.shape[1])
        padded = [*camera_images, *[torch.zeros_like(camera_images[0])] * (views - len(camera_images))]
        features = torch.stack(padded[:views], dim=1).flatten(0, 1)
        with patched(embedder, num_image_token=counts.pop()):
            return embedder._forward_vlm(features, [[1] * views] * int(image_masks.shape[0]), image_masks,
                                         text_prompts, return_cls_only)

    def _image_features(self, own, pixel_values: torch.Tensor, **kwargs):
        """InternVL's `get_image_features`, or grafted: the cached features [B x views, T, C] through the
        pass-through and the projector (no CLS to drop, no pixel shuffle: the cache holds the grid the projector
        takes). The projector sees one row per sample ([B, views x T, C]), so a fused pass's projectors
        (graftcache.graft.FusedProjector) each take their own cell's samples."""
        if not self.grafted:
            return own(pixel_values, **kwargs)
        tower, connector = self._tower_and_connector()
        features = tower(pixel_values).last_hidden_state
        per_sample = features.unflatten(0, (-1, self.config.max_views)).flatten(1, 2)
        tokens = connector(per_sample).reshape(*features.shape[:2], -1)
        return BaseModelOutputWithPooling(last_hidden_state=pixel_values, pooler_output=tokens)

    # ------------------------------------------------------------------------------ native tower
    def _native_pixels(self, images: torch.Tensor) -> torch.Tensor:
        """[0, 1] frames -> the embedder's own pixel step (uint8 quantise, bicubic resize, ImageNet normalise)."""
        from lerobot.policies.evo1.internvl3_embedder import IMAGENET_MEAN, IMAGENET_STD, _batched_pixel_values

        self._check_native(images)
        embedder = self.policy.model.embedder
        return _batched_pixel_values([images.to(self.device)], 1, embedder.image_size, torch.tensor(IMAGENET_MEAN),
                                     torch.tensor(IMAGENET_STD), embedder.model_dtype, self.device)

    @torch.no_grad()
    def native_patch_grid(self, images: torch.Tensor) -> torch.Tensor:
        """InternViT's patch grid before the pixel shuffle [B, gh, gw, C] (its CLS token dropped, as InternVL's
        `default` feature selection drops it)."""
        internvl = self._vision_owner
        layer = internvl.config.vision_feature_layer
        out = internvl.vision_tower(pixel_values=self._native_pixels(images), output_hidden_states=layer != -1)
        hidden = out.last_hidden_state if layer == -1 else out.hidden_states[layer]
        if internvl.config.vision_feature_select_strategy == "default":
            hidden = hidden[:, 1:]
        side = int(round(hidden.shape[1] ** 0.5))
        return hidden.reshape(hidden.shape[0], side, side, hidden.shape[-1]).float()

    @torch.no_grad()
    def native_tokens(self, images: torch.Tensor) -> torch.Tensor:
        """The projector's tokens [B, T, D], what InternVL scatters into a camera's `<IMG_CONTEXT>` slots."""
        return self._vision_owner.get_image_features(pixel_values=self._native_pixels(images)).pooler_output.float()

    # ----------------------------------------------------------------------------- policy loss
    def prepare(self, raw: Mapping[str, Any]) -> dict[str, Any]:
        """lerobot's preprocessor, with its padding of the action chunk (and of the mask saying so) to
        `max_action_dim` cut back to the real dims: the policy pads them again itself (`_prepare_actions`), and
        the fit reads the batch's `action` as the normalised target of the real dims, as for every backbone."""
        batch = super().prepare(raw)
        for key in (ACTION, "action_mask"):
            if batch.get(key) is not None:  # None: a batch without actions (a policy acting: graftcache.export)
                batch[key] = batch[key][..., : self.action_dim]
        return batch

    @staticmethod
    def _uniform(noise: torch.Tensor) -> torch.Tensor:
        """graftcache's standard-normal noise as EVO1's uniform noise in [-1, 1]: u = 2 Phi(z) - 1 = erf(z / sqrt 2)
        (each normal draw through its own CDF: exactly uniform, and a fixed draw stays fixed)."""
        return torch.erf(noise / math.sqrt(2.0))

    def sample_time(self, batch_size: int) -> torch.Tensor:
        """EVO1's own draw (Beta(2, 2) in [0.02, 0.98], symmetric, so the same as a noise level)."""
        return torch.distributions.Beta(2.0, 2.0).sample((batch_size,)).clamp(0.02, 0.98).to(self.device)

    def _context(self, batch: Mapping[str, Any]) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor]:
        """The head's context as lerobot builds it: (context tokens, key padding mask, embodiment ids)."""
        policy = self.policy
        prompts = policy._normalize_task_batch(batch)
        images, masks = policy._collect_image_batches(batch)
        states, _ = policy._prepare_state(batch)
        embodiment = policy._get_embodiment_ids(batch, states.shape[0])
        fused, context = policy._compute_fused_tokens(prompts, images, masks)
        return policy.model.action_head._prepare_context(fused, states, embodiment, context)

    def _velocity(self, context, padding, embodiment, seq: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
        """One pass of EVO1's head: the velocity [B, chunk * max_action_dim] at `seq` and time indices [B]."""
        head = self.policy.model.action_head
        time_emb = head.time_pos_enc(1000)[0, index.to(context.device)].to(head.dtype)
        x = head._project_actions(seq, embodiment).to(head.dtype)
        for block in head.transformer_blocks:
            x = block(x, context.to(head.dtype), time_emb, padding)
        x = head.norm_out(x)
        pooled = head.seq_pool_proj(x.reshape(x.shape[0], -1)) if head.horizon > 1 else x.squeeze(1)
        return head.mlp_head(pooled, embodiment)

    def _flow_losses(self, batch: Mapping[str, Any], noise: torch.Tensor, time: torch.Tensor) -> torch.Tensor:
        """EVO1's `forward` with the given draws: the squared velocity error per element [B, chunk, max_dim]."""
        policy = self.policy
        with policy._maybe_autocast():
            context, padding, embodiment = self._context(batch)
            actions, mask = policy._prepare_actions(batch)
            mask = mask.to(policy._compute_dtype)
            t = (1 - time).to(self.device, policy._compute_dtype)
            index = (t * 999).long().clamp_(0, 999)
            noise = self._uniform(noise.to(self.device, policy._compute_dtype)) * mask
            x_t = (1 - t).view(-1, 1, 1) * noise + t.view(-1, 1, 1) * (actions * mask)
            velocity = self._velocity(context, padding, embodiment, x_t, index)
        target = actions.float() - noise.float()
        return (velocity.float().view(target.shape) - target) ** 2

    @torch.no_grad()
    def _predict_chunk(self, batch: Mapping[str, Any], noise: torch.Tensor, num_steps: int) -> torch.Tensor:
        """`Evo1Policy.predict_action_chunk` from `noise` with `num_steps` Euler steps, cut to the real dims."""
        policy, head = self.policy, self.policy.model.action_head
        policy.eval()
        with policy._maybe_autocast():
            context, padding, embodiment = self._context(batch)
            size = context.shape[0]
            mask = head._expand_action_mask(policy._prepare_inference_action_mask(size), size, head.per_action_dim,
                                            context.device, context.dtype)
            seq = self._uniform(noise.to(context.device, context.dtype)).view_as(mask) * mask
            steps = max(1, int(num_steps))
            dt = 1.0 / steps
            for i in range(steps):
                index = torch.full((size,), min(int(i / steps * 999), 999), dtype=torch.long)
                velocity = self._velocity(context, padding, embodiment, seq * mask, index).view_as(mask) * mask
                seq = seq + dt * velocity
        return (seq * mask).float()[:, :, : self.action_dim]

    @classmethod
    def postprocessor_input(cls, config, actions: torch.Tensor) -> torch.Tensor:
        """EVO1's `select_action` emits actions at the padded `max_action_dim`, and its postprocessor unnormalises
        at that width (its stats padded to it) before cutting to the real dims: the real dims are padded with zeros
        for it (the padding never reaches the output). Offline scoring's `unnormalize` and an export's
        postprocessor both feed it this way."""
        pad = config.max_action_dim - actions.shape[-1]
        return torch.nn.functional.pad(actions, (0, pad)) if pad > 0 else actions
