"""X-VLA (lerobot 0.6, Florence-2 DaViT + BART encoder + soft-prompted transformer) as a graftable backbone.

Vision path (modeling_xvla.py `_prepare_images`, `forward_vlm`; transformers florence2): the preprocessor
rescales to ImageNet mean/std, `_prepare_images` stacks every camera into [B, V, 3, H, W] (optionally
resize-with-pad), and `forward_vlm` runs every valid view through `vlm.get_image_features`: DaViT (4 strided
conv stages, /32) -> [C, H/32, W/32] -> `multi_modal_projector` (2-D position embedding, one spatial-mean
token prepended, Linear to `projection_dim`, LayerNorm) = 1 + (H/32)(W/32) tokens per view. The tokens of
view 0 are prepended to the text and go through the Florence-2 (BART) encoder, the "LM"; the tokens of the
other views bypass it and enter the action transformer directly as `aux_visual_inputs`.

Graft slots: every real camera. All views share the one tower and projector in the policy, so replacing
them replaces the image input of both routes; view 0 reaches the LM, the other views the action transformer,
exactly as the policy's own tokens do. The graft gives (H/32)(W/32) tokens (the grid, pooled); the projector's
extra spatial-mean token is part of the connector the graft replaces (the `native` control keeps it: its
cached connector tokens are 1 + grid). The projector's width is `projection_dim` (= the BART width), and no
scale follows it (BART scales only the word embeddings it looks up).

X-VLA's policy loss is not lerobot's velocity flow: it predicts the clean chunk from x_t = t*noise + (1-t)*action
and scores it with the action space's own loss (`action_space.compute_loss`: MSE on the real dims for the
"auto" space). `loss` and `predict` therefore call the model's own parts (`forward_vlm`, `action_space`,
`transformer`) with the given noise and time instead of the policy's `forward`/`generate_actions`, which draw
their own (tests/backbones/test_xvla.py checks both against lerobot's under the same RNG draws).
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Mapping
from typing import Any

import torch
from torch import nn
from transformers.modeling_outputs import BaseModelOutputWithPooling

from graftcache.backbones.activation_checkpointing import WrappedActivationCheckpointing
from graftcache.backbones.base import BackboneAdapter, is_empty_camera
from graftcache.backbones.batches import ACTION_PAD
from graftcache.backbones.tiny_assets import PALIGEMMA_DIR
from graftcache.backbones.xvla.spec import SPEC
from graftcache.errors import BackboneError


def conv_grid(size: tuple[int, int], vision) -> tuple[int, int]:
    """DaViT's output grid for an input of `size` (its strided conv embeddings, stage by stage)."""
    h, w = size
    for k, s, p in zip(vision.patch_size, vision.patch_stride, vision.patch_padding):
        h, w = (h + 2 * p - k) // s + 1, (w + 2 * p - k) // s + 1
    return h, w


class XVLAAdapter(WrappedActivationCheckpointing, BackboneAdapter):
    name = "xvla"
    spec = SPEC

    def _patch_graft(self, graft) -> None:
        """Grafted, Florence-2's `get_image_features` projects the cached features (undone by reset)."""
        graft.shadow(self._vision_owner, "get_image_features", self._image_features)

    # ------------------------------------------------------------------------------ construction
    @classmethod
    def _construct(cls, config, marker: dict | None) -> nn.Module:
        """XVLAPolicy's own constructor. Built on the meta device, Florence-2's BART word embedding comes out
        untied from its encoder's copy: tied again, as transformers ties it, so the policy holds (and counts)
        that tensor once."""
        policy = super()._construct(config, marker)
        bart = policy.model.vlm.language_model  # its own tie_weights also ties the decoder, which X-VLA drops
        bart.encoder.embed_tokens.weight = bart.shared.weight
        return policy

    @classmethod
    def _checkpoint_keys(cls, policy: nn.Module, file_keys: Iterable[str]) -> dict[str, str]:
        """As XVLAPolicy.from_pretrained reads a checkpoint: the tied word embedding under whichever of its two
        names the file holds. A checkpoint in the old vendored Florence-2 layout (its image projection must be
        transposed, not renamed) is refused with the one-time conversion, lerobot's own loader, that fixes it."""
        from lerobot.policies.xvla.modeling_xvla import _is_vendored_florence_state_dict

        keys = {k: k for k in file_keys}
        if _is_vendored_florence_state_dict(keys):
            raise BackboneError("an X-VLA checkpoint in the old vendored Florence-2 layout: convert it once with "
                                "lerobot (XVLAPolicy.from_pretrained(old).save_pretrained(new)) and load the new "
                                "folder")
        shared = "model.vlm.language_model.shared.weight"
        embed = "model.vlm.language_model.encoder.embed_tokens.weight"
        for a, b in ((shared, embed), (embed, shared)):
            if a in keys and b not in keys:
                keys[b] = keys[a]
        return keys

    @classmethod
    def _processor_overrides(cls, config, marker: dict | None, device: str) -> tuple[dict, dict]:
        pre, post = super()._processor_overrides(config, marker, device)
        if marker is not None:  # the saved tokenizer path points into the package that saved it
            from transformers import AutoTokenizer

            pre["tokenizer_processor"] = {"tokenizer": AutoTokenizer.from_pretrained(PALIGEMMA_DIR)}
        return pre, post

    @classmethod
    def _make_processors(cls, config, stats: dict, marker: dict | None):
        from lerobot.policies.xvla.processor_xvla import make_xvla_pre_post_processors

        if marker is not None:
            config.tokenizer_name = str(PALIGEMMA_DIR)
        return make_xvla_pre_post_processors(config, dataset_stats=stats)

    # ------------------------------------------------------------------------------ geometry
    @property
    def _vision_owner(self) -> nn.Module:
        return self.policy.model.vlm  # transformers Florence2Model

    @classmethod
    def _grid_of_config(cls, config, marker: dict | None) -> tuple[int, int]:
        """The DaViT grid of the images `_prepare_images` hands the tower: resized-with-pad if the config says
        so, else the first real camera's size as the dataset declares it."""
        size = config.resize_imgs_with_padding
        if size is None:
            real = [f for k, f in config.image_features.items() if not is_empty_camera(k)]
            if not real:
                raise BackboneError("xvla config declares no real camera")
            size = tuple(real[0].shape[-2:])
        return conv_grid(tuple(size), config.get_florence_config().vision_config)

    @property
    def max_action_dim(self) -> int:
        """The action space's model-facing width (the "auto" space pads the real dims to `max_action_dim`)."""
        return self.policy.model.dim_action

    # ------------------------------------------------------------------------------ native tower
    def _native_pixels(self, images: torch.Tensor) -> torch.Tensor:
        """[0, 1] pixels -> ImageNet-normalised (the preprocessor's step) -> `_prepare_images`'s view 0."""
        from lerobot.policies.xvla.processor_xvla import IMAGENET_STATS

        if self.grafted:
            raise BackboneError(f"{self.name}: the native tower was removed by graft(); read it before grafting")
        if images.ndim != 4 or images.shape[1] != 3:
            raise BackboneError(f"{self.name}: native images must be [B, 3, H, W] in [0, 1], got {tuple(images.shape)}")
        x = images.to(self.device)
        mean = torch.tensor(IMAGENET_STATS["mean"], device=x.device, dtype=x.dtype).view(1, 3, 1, 1)
        std = torch.tensor(IMAGENET_STATS["std"], device=x.device, dtype=x.dtype).view(1, 3, 1, 1)
        stacked, _ = type(self.policy)._prepare_images(self.policy, {self.camera_keys[0]: (x - mean) / std})
        return stacked[:, 0]

    @torch.no_grad()
    def native_patch_grid(self, images: torch.Tensor) -> torch.Tensor:
        """DaViT's last stage [B, C, gh, gw] as [B, gh, gw, C]."""
        tower, _ = self._tower_and_connector()
        hidden = tower(self._native_pixels(images)).last_hidden_state.float()
        return hidden.permute(0, 2, 3, 1).contiguous()

    def _image_features(self, own, vlm: nn.Module, pixel_values: torch.Tensor, **kwargs):
        """Florence-2's `get_image_features`, or grafted: the cached features of the valid views [views, T, C]
        through the pass-through and the projector a sample a row, [B, cameras x T, C] (every sample has the same
        real cameras), so that a fused projector (graftcache.graft.FusedProjector) routes rows."""
        if not self.grafted:
            return own(vlm, pixel_values, **kwargs)
        tower, connector = self._tower_and_connector()
        features = tower(pixel_values).last_hidden_state
        samples = len(features) // len(self.camera_keys)  # forward_vlm keeps the real cameras' views
        tokens = connector(features.reshape(samples, -1, features.shape[-1]))
        return BaseModelOutputWithPooling(last_hidden_state=features,
                                          pooler_output=tokens.reshape(len(features), -1, tokens.shape[-1]))

    def _feature_images(self, batch: Mapping[str, Any]) -> tuple[torch.Tensor, torch.Tensor]:
        """Cached features as `_prepare_images` returns pixels: stacked views [B, V, T, C], masks [B, V], padded
        with masked zero views to `num_image_views`."""
        images, masks = super()._feature_images(batch)
        images, masks = torch.stack(images, dim=1), torch.stack(masks, dim=1)
        missing = (self.config.num_image_views or 0) - images.shape[1]
        if missing > 0:
            images = torch.cat([images, images.new_zeros(images.shape[0], missing, *images.shape[2:])], dim=1)
            masks = torch.cat([masks, masks.new_zeros(masks.shape[0], missing)], dim=1)
        return images, masks

    # ----------------------------------------------------------------------------- policy loss
    def _encode(self, batch: Mapping[str, Any]) -> tuple[dict, dict[str, torch.Tensor], torch.dtype]:
        """(model inputs, `forward_vlm`'s outputs, the model's dtype) for a prepared batch."""
        model = self.policy.model
        dtype = model._get_target_dtype()
        inputs = self.policy._build_model_inputs(dict(batch))
        enc = model.forward_vlm(inputs["input_ids"], inputs["image_input"].to(dtype), inputs["image_mask"])
        return inputs, enc, dtype

    def _denoise(self, inputs: dict, enc: dict, x_t: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        """One call of X-VLA's transformer: the clean chunk predicted from `x_t` at noise level `t`."""
        model = self.policy.model
        proprio, x_t = model.action_space.preprocess(inputs["proprio"].to(x_t.dtype), x_t)
        return model.transformer(domain_id=inputs["domain_id"], action_with_noise=x_t, t=t, proprio=proprio, **enc)

    def loss(self, batch: Mapping[str, Any], noise: torch.Tensor | None = None,
             time: torch.Tensor | None = None) -> torch.Tensor:
        """Per-sample X-VLA loss [B]: the action space's own loss (`compute_loss`, summed over its terms as
        lerobot's `forward` sums them) on each sample's non-padded chunk steps. `noise` [B, chunk, dim_action]
        and `time` [B] (the noise level) default to X-VLA's own draws."""
        inputs, enc, dtype = self._encode(batch)
        target = self.policy._prepare_action_targets(dict(batch)).to(dtype)
        size = target.shape[0]
        if time is None:  # modeling_xvla.py: stratified uniform noise levels
            time = (torch.rand(1, device=self.device) + torch.arange(size, device=self.device) / size) % (1 - 1e-5)
        noise = torch.randn_like(target) if noise is None else noise.to(dtype)
        t = time.to(dtype)
        x_t = noise * t.view(-1, 1, 1) + target * (1 - t).view(-1, 1, 1)
        pred = self._denoise(inputs, enc, x_t, t)
        pad = batch.get(ACTION_PAD)
        valid = torch.ones(target.shape[:2], dtype=torch.bool, device=target.device) if pad is None else ~pad.bool()
        space = self.policy.model.action_space
        losses = []
        for i in range(size):
            keep = valid[i] if valid[i].any() else torch.ones_like(valid[i])  # an all-padded chunk: nothing to mask
            terms = space.compute_loss(pred[i:i + 1, keep], target[i:i + 1, keep])
            losses.append(sum(terms.values()))
        return torch.stack(losses)

    @torch.no_grad()
    def _predict_chunk(self, batch: Mapping[str, Any], noise: torch.Tensor, num_steps: int) -> torch.Tensor:
        """`XVLAModel.generate_actions` with `noise` as its start instead of a fresh draw."""
        self.policy.eval()
        inputs, enc, dtype = self._encode(batch)
        x1 = noise.to(dtype)
        action = torch.zeros_like(x1)
        steps = max(1, int(num_steps))
        for i in range(steps, 0, -1):
            t = torch.full((x1.shape[0],), i / steps, device=x1.device, dtype=dtype)
            action = self._denoise(inputs, enc, x1 * t.view(-1, 1, 1) + action * (1 - t).view(-1, 1, 1), t)
        return self.policy.model.action_space.postprocess(action)

    def _recompute_slots(self) -> Iterator[tuple[nn.Module, str]]:
        """Every layer of the BART encoder (the LM) and every block of the action transformer."""
        for layer in self._vision_owner.language_model.encoder.layers:
            yield layer, "forward"
        for block in self.policy.model.transformer.blocks:
            yield block, "forward"
