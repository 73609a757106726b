"""VLA-JEPA (lerobot 0.6: Qwen3-VL-2B + a DiT flow-matching action head, a JEPA world model in training) as a
graftable backbone.

What runs when (modeling_vla_jepa.py): the policy builds one Qwen3-VL chat prompt per sample - every camera's
current frame as an image, then the task, 24 world-model action tokens and 32 embodied-action tokens - and takes
the last decoder layer's hidden states (before the final norm) at those tokens. The DiT action head
cross-attends to the embodied-action states and is trained by flow matching (`action_loss`, the velocity MSE over
the real action steps, repeated over 8 noise draws per sample); inference integrates it from noise in 4 Euler steps.
The world model - a frozen V-JEPA2 video encoder and an action-conditioned predictor fed the action-token states -
only adds `0.1 * wm_loss` (L1 on the next V-JEPA2 frame embeddings of an 8-frame clip) in training; inference never
runs it. graftcache builds the policy without it (graftcache.backbones.vla_jepa.tiny.construct): its policy loss
is the policy's own action loss, `action_loss`, with one noise draw per sample and step (the 8 repeats are a variance
reduction of the same expectation; graftcache's steps draw their own noise), and the world-model term, which needs
future video the cache does not hold and a second 300M-parameter encoder, is left out.

Vision path (transformers qwen3_vl): Qwen's processor resizes each frame (`smart_resize`: multiples of 32 between
its min and max pixels), cuts 16 px patches ordered by 2x2 merge block, and writes one `<|image_pad|>` per merged
block. `Qwen3VLModel.get_image_features` runs the ViT (`visual.blocks`) and its `merger` (LayerNorm, 2x2 concat,
MLP into the LM width) and scatters the tokens into the image pads, camera after camera; three `deepstack` mergers
also add features of blocks 5, 11 and 17 to the hidden states of the first three LM layers at those positions.
Tokens per camera: LIBERO's 256 px -> 16x16 patches -> 8x8 = 64 with Qwen3-VL-2B's processor bounds.

Graft slots: the image-pad positions, every camera. The tower (`visual.blocks`) becomes the pass-through and the
merger the projector; Qwen's `get_image_features` is shadowed on the instance so that, grafted, it projects the
cached features, with no deepstack features (a grafted encoder replaces the whole tower, side paths included; the
`native` control therefore differs from the ungrafted policy by exactly those deepstack additions, which the tests
pin). The prompt is the policy's own, built by its own `build_inputs` from blank frames of the grid's size, so pad
positions, M-RoPE positions and masks are the policy's; the cached features then stand in for `pixel_values`.

The head draws its noise with `torch.randn_like` / `torch.randn` and its time with `sample_time`; `loss` and
`predict` run lerobot's own code with those draws given (`given_draws`). graftcache's flow time is the noise
fraction (lerobot's pi0 convention: Beta(1.5, 1)); VLA-JEPA's t is the clean fraction, so t = 1 - time.
"""

from __future__ import annotations

import contextlib
import json
import warnings
from collections.abc import Iterable, Iterator, Mapping
from pathlib import Path
from typing import Any

import torch
from torch import nn

from graftcache.backbones.activation_checkpointing import WrappedActivationCheckpointing
from graftcache.backbones.base import BackboneAdapter, vlm_folder
from graftcache.backbones.batches import ACTION
from graftcache.backbones.given_draws import given_noise, shadowed
from graftcache.backbones.patching import patched
from graftcache.backbones.policy_loss import FlowLoss
from graftcache.backbones.qwen_vl import (
    check_slots,
    image_token_counts,
    merged_grid,
    prompt_grid,
    qwen3_vl_image_features,
    raster_patches,
    tied_head_keys,
)
from graftcache.backbones.vla_jepa.spec import SPEC
from graftcache.backbones.vla_jepa.tiny import QWEN3_VL_DIR, construct
from graftcache.errors import BackboneError
from graftcache.graft import feature_key

QWEN_MODEL = "Qwen3-VL config and processor"


def image_processor_config(folder: Path) -> dict:
    """The image processor's saved settings in a Qwen folder: preprocessor_config.json (the hub's layout) or the
    `image_processor` entry of processor_config.json (what transformers 5 saves)."""
    for name, key in (("preprocessor_config.json", None), ("processor_config.json", "image_processor")):
        path = folder / name
        if path.is_file():
            data = json.loads(path.read_text())
            data = data.get(key, {}) if key else data
            if "size" in data:
                return data
    raise BackboneError(f"{folder}: no Qwen image processor config (preprocessor_config.json or processor_config.json)")


@contextlib.contextmanager
def given_draws(head: nn.Module, noise: torch.Tensor, time: torch.Tensor | None = None) -> Iterator[None]:
    """The action head's noise (and, given, its time t) fixed for the block."""
    from lerobot.policies.vla_jepa import action_head

    samplers = {} if time is None else {"sample_time": lambda size, device, dtype: time.to(device, dtype)}
    with given_noise(action_head, noise, VLAJEPAAdapter.name), shadowed(head, **samplers):
        yield


class VLAJEPAAdapter(WrappedActivationCheckpointing, FlowLoss, BackboneAdapter):
    name = "vla_jepa"
    spec = SPEC

    def _patch_graft(self, graft) -> None:
        """Grafted, Qwen's `get_image_features` projects the cached features and the prompt is built for them
        (undone by reset)."""
        graft.shadow(self._qwen, "get_image_features", self._image_features)
        graft.shadow(self.policy.model.qwen, "build_inputs", self._build_inputs)

    # ------------------------------------------------------------------------------ construction
    @classmethod
    def _construct(cls, config, marker: dict | None) -> nn.Module:
        """VLAJEPAPolicy without its world model, Qwen3-VL built from the Qwen folder's config (the checkpoint
        holds the weights). Built on the meta device, the LM head comes out untied from the word embedding: tied
        again, as transformers ties it, so the policy holds (and counts) that tensor once."""
        policy = construct(config, cls._qwen_folder(config, marker))
        policy.model.qwen.model.tie_weights()
        return policy

    @classmethod
    def _checkpoint_keys(cls, policy: nn.Module, file_keys: Iterable[str]) -> dict[str, str]:
        """Qwen3-VL-2B ties its LM head to the word embedding; safetensors keeps one of the two names: read the
        other from it."""
        return tied_head_keys(file_keys, "model.qwen.model.lm_head.weight",
                              "model.qwen.model.model.language_model.embed_tokens.weight")

    @classmethod
    def _qwen_folder(cls, config, marker: dict | None) -> Path:
        """The Qwen3-VL folder (config, processor) `qwen_model_name` names (graftcache.backbones.base.vlm_folder)."""
        return vlm_folder(config.qwen_model_name, marker, QWEN3_VL_DIR, f"VLA-JEPA's {QWEN_MODEL}")

    @classmethod
    def _make_processors(cls, config, stats: dict, marker: dict | None):
        from lerobot.policies.vla_jepa.processor_vla_jepa import make_vla_jepa_pre_post_processors

        return make_vla_jepa_pre_post_processors(config, dataset_stats=stats)

    # ------------------------------------------------------------------------------ geometry
    @property
    def _qwen(self) -> nn.Module:
        return self.policy.model.qwen.model.model  # Qwen3VLModel

    @property
    def _vision_owner(self) -> nn.Module:
        return self._qwen.visual  # Qwen3VLVisionModel

    @classmethod
    def _grid_of_config(cls, config, marker: dict | None) -> tuple[int, int]:
        """The merged grid of the frames the policy's inference sees under the Qwen folder's image processor: the
        first camera's size as the config declares it, or `resize_images_to` where set (`predict_action` resizes
        to it; lerobot's training forward does not)."""
        cameras = list(config.image_features.values())
        if not cameras:
            raise BackboneError("vla_jepa config declares no camera")
        size = tuple(config.resize_images_to or cameras[0].shape[-2:])
        processor = image_processor_config(cls._qwen_folder(config, marker))
        bounds = processor["size"]
        return merged_grid(size, processor["patch_size"], processor["merge_size"], bounds["shortest_edge"],
                           bounds["longest_edge"])

    @property
    def max_action_dim(self) -> int:
        """VLA-JEPA's head works in the real action width (no padding)."""
        return self.action_dim

    # ------------------------------------------------------------------------------ images
    def _image_features(self, own, qwen: nn.Module, pixel_values: torch.Tensor, image_grid_thw=None, **kwargs):
        """Qwen's `get_image_features`, or grafted: the cached features of every camera through the pass-through and
        the projector, and no deepstack features (VLA-JEPA's "none" is an empty list)."""
        if not self.grafted:
            return own(qwen, pixel_values, image_grid_thw, **kwargs)
        return qwen3_vl_image_features(*self._tower_and_connector(), qwen, pixel_values, image_grid_thw,
                                       len(self.config.image_features), deepstack=[])

    def _vision(self, images: torch.Tensor):
        """[B, 3, H, W] in [0, 1] through the policy's own inference path - `predict_action`'s resize to
        `resize_images_to` where set, the processor call (float frames, no rescale), Qwen's own
        `get_image_features` under the policy's autocast: its output for those images."""
        from lerobot.policies.vla_jepa.modeling_vla_jepa import _get_autocast_context

        self._check_native(images)
        if self.config.resize_images_to is not None:
            images = torch.nn.functional.interpolate(images, size=tuple(self.config.resize_images_to), mode="area")
        processor = self.policy.model.qwen.processor.image_processor
        inputs = processor(images=list(images.clamp(0, 1).float()), do_rescale=False, return_tensors="pt")
        thw = inputs["image_grid_thw"].to(self.device)
        with _get_autocast_context(self.device.type, torch.bfloat16):
            out = type(self._qwen).get_image_features(self._qwen, inputs["pixel_values"].to(self.device), thw)
        return out, thw

    @torch.no_grad()
    def native_patch_grid(self, images: torch.Tensor) -> torch.Tensor:
        """The ViT's last block before the merger, [B, gh, gw, C] at patch resolution (2x the merged grid), in
        raster order (Qwen orders patches by 2x2 merge block)."""
        out, thw = self._vision(images)
        m = self._vision_owner.spatial_merge_size
        _, gh, gw = thw[0].tolist()
        return raster_patches(out.last_hidden_state, len(images), gh, gw, m).float()

    @torch.no_grad()
    def native_tokens(self, images: torch.Tensor) -> torch.Tensor:
        """Post-merger tokens [B, gh/2 * gw/2, D], in the order Qwen scatters them into the prompt."""
        out, _ = self._vision(images)
        return torch.stack(out.pooler_output).float()

    def _feature_images(self, batch: Mapping[str, Any], training: bool = True) -> dict[str, Any]:
        """Grafted stand-in for VLAJEPAPolicy._prepare_model_inputs: lerobot's own conversion (state, actions,
        tasks) with 1-pixel blank frames for the cameras, then each sample's cached features [T, C], camera after
        camera, in place of its images (the grafted `build_inputs` makes the prompt from them)."""
        images, _ = super()._feature_images(batch)
        counts = {f.shape[1] for f in images}
        if len(counts) != 1:
            raise BackboneError(f"{self.name}: cameras carry different token counts ({sorted(counts)})")
        size = images[0].shape[0]
        blanks = {k: torch.zeros(size, 3, 1, 1, device=images[0].device) for k in self.config.image_features}
        rest = {k: v for k, v in batch.items() if not k.startswith(feature_key(""))}
        inputs = type(self.policy)._prepare_model_inputs(self.policy, {**rest, **blanks}, training=training)
        inputs["images"] = [[f[b] for f in images] for b in range(size)]
        return inputs

    def _build_inputs(self, own, interface: nn.Module, images, instructions, action_prompt, embodied_prompt):
        """Qwen3VLInterface.build_inputs, or grafted: the policy's prompt for blank frames whose processed grid is
        the cached features' (the processor's pixel bounds set to that frame for the call), with the features of
        every image, sample after sample, camera after camera, as `pixel_values`."""
        if not self.grafted:
            return own(interface, images, instructions, action_prompt, embodied_prompt)
        features = [f for views in images for f in views]
        gh, gw = prompt_grid(self.name, "VLA-JEPA", self.token_grid, features[0].shape[0])
        processor = interface.processor.image_processor
        factor = processor.patch_size * processor.merge_size
        frames = [[torch.zeros(3, gh * factor, gw * factor) for _ in views] for views in images]
        pixels = gh * gw * factor ** 2
        with patched(processor, size=type(processor.size)(shortest_edge=pixels, longest_edge=pixels)):
            inputs = own(interface, frames, instructions, action_prompt, embodied_prompt)
        check_slots(self.name, {f.shape[0] for f in features},
                    set(image_token_counts(inputs["image_grid_thw"], processor.merge_size)))
        inputs["pixel_values"] = torch.cat(features)
        return inputs

    # ----------------------------------------------------------------------------- policy loss
    def sample_time(self, batch_size: int) -> torch.Tensor:
        """The action head's own draw, as a noise level (1 - its t)."""
        return self.noise_level(self.policy.model.action_model.sample_time(batch_size, self.device, torch.float32))

    def _flow_losses(self, batch: Mapping[str, Any], noise: torch.Tensor, time: torch.Tensor) -> torch.Tensor:
        """lerobot's VLA-JEPA forward (one noise draw per sample) with the given draws; the per-element velocity
        error from the action decoder's output (lerobot reduces the loss to a scalar)."""
        model, config = self.policy.model, self.config
        velocity = []
        hook = model.action_model.action_decoder.register_forward_hook(lambda m, args, out: velocity.append(out))
        try:
            with patched(config, repeated_diffusion_steps=1), given_draws(model.action_model, noise, 1 - time), \
                    warnings.catch_warnings():
                # lerobot asks CPU autocast for float32 around the head; torch declines (the head runs in fp32)
                warnings.filterwarnings("ignore", "In CPU autocast, but the target dtype is not supported")
                self.policy.forward(dict(batch))
        finally:
            hook.remove()
        action = batch[ACTION][:, -config.chunk_size:].float()
        target = action - noise.to(action)
        return (velocity[0].float() - target) ** 2

    @torch.no_grad()
    def _predict_chunk(self, batch: Mapping[str, Any], noise: torch.Tensor, num_steps: int) -> torch.Tensor:
        """`VLAJEPAPolicy.predict_action_chunk` from `noise` with `num_steps` Euler steps. Grafted, its resize to
        `resize_images_to` is off for the call: it acts on frames, and the cached features are already at the
        grid that resize gives (token_grid)."""
        head, config = self.policy.model.action_model, self.config
        resize = None if self.grafted else config.resize_images_to
        with patched(head, num_inference_timesteps=int(num_steps)), patched(config, resize_images_to=resize), \
                given_draws(head, noise):
            return self.policy.predict_action_chunk(dict(batch))

    def _switch_recompute(self, on: bool) -> None:
        """The wrapped layers, and Qwen's KV cache off meanwhile (as transformers turns it off under its own
        activation checkpointing): a recomputed layer would append its keys and values to the cache a second time. The
        policy's single forward never reads that cache."""
        super()._switch_recompute(on)  # off: every change undone, the cache's switch too
        if on and not any(change.attribute == "use_cache" for change in self.recompute_patches.changes):
            self.recompute_patches.set(self._qwen.language_model.config, "use_cache", False)

    def _recompute_slots(self) -> Iterator[tuple[nn.Module, str]]:
        """Every decoder layer of the Qwen3 LM and every block of the DiT action head."""
        for layer in self._qwen.language_model.layers:
            yield layer, "forward"
        for block in self.policy.model.action_model.model.transformer_blocks:
            yield block, "forward"
