"""Wall-X (lerobot 0.6 `wall_x`: Qwen2.5-VL's ViT, a Qwen2.5 LM whose MLPs are hard-routed experts, a flow action
head on the action tokens of the same sequence) as a graftable backbone.

Vision path (modeling_wall_x.py `WallXPolicy.preprocess_inputs`, `Qwen2_5_VLMoEForAction.train_step_forward` /
`predict`): the policy itself resizes every camera to 256 px on its longer side and smart_resizes it to multiples
of 28 (LIBERO's 256 px -> 252 px), Qwen's image processor applies its own pixel bounds, cuts 14 px patches in 2x2
merge-block order and the prompt gets one `<|image_pad|>` per merged block; `visual` (ViT + `merger` into the LM
width) embeds the images and its `pooler_output` is scattered into the image-pad positions, sample after sample,
camera after camera. Tokens per camera: 252 px -> 18x18 patches -> 9x9 = 81 with Qwen's own bounds.

Graft slots: those image-pad positions, every camera. The ViT blocks become the pass-through and the merger (the
connector) the projector; `visual.forward` is shadowed on the instance so that, grafted, it projects the cached
features it is given as `pixel_values` (unchanged otherwise). `preprocess_inputs` (the policy's image method) is
overridden while grafted: it runs lerobot's own on blank frames of the dataset's size with the image processor's
pixel bounds set to the cached grid, so input ids, M-RoPE positions, masks and MoE routing are the policy's own,
then puts the features where the pixels were. Wall-X casts `pixel_values` to the ViT's dtype (bf16) before the
ViT: the features reach the projector rounded the same way.

Policy loss: Wall-X's flow loss only. In flow mode (`prediction_mode='diffusion'`) its prompt's assistant turn holds
only `<|action|>` tokens, which `preprocesser_call` masks out of the labels, so `labels` is None and the model's
cross-entropy term is never computed: the loss is `flow_loss_weight` x the flow MSE. Wall-X draws its time and
noise inside `ActionHead.forward` / `predict` (`sample_time`, `torch.randn_like`, `torch.randn`); `loss` and
`predict` run lerobot's own code with the sampler shadowed and those two calls answered with the given draws
(`graftcache.backbones.given_draws.given_noise`). Wall-X's time runs the other way from graftcache's noise level (its
x_t = (1 - t) noise + t action, pi0's x_t = t noise + (1 - t) action) and its draw (1 - Beta(1.5, 1)) x 0.999 is
exactly 1 - graftcache's: the given time is passed on as 1 - time.
"""

from __future__ import annotations

import contextlib
import functools
import inspect
from collections.abc import Iterable, Iterator, Mapping
from pathlib import Path
from typing import Any

import torch
from torch import nn
from transformers.modeling_outputs import BaseModelOutputWithPooling

from graftcache.backbones.activation_checkpointing import WrappedActivationCheckpointing
from graftcache.backbones.base import BackboneAdapter, vlm_folder
from graftcache.backbones.batches import STATE
from graftcache.backbones.given_draws import given_noise, shadowed
from graftcache.backbones.patching import patched
from graftcache.backbones.policy_loss import FlowLoss
from graftcache.backbones.qwen_vl import (
    TowerReads,
    merged_grid,
    projected_rows,
    prompt_grid,
    tied_head_keys,
    vit_outputs,
)
from graftcache.backbones.wall_x.spec import SPEC
from graftcache.backbones.wall_x.tiny import WALLX_DIR, construct, load_processor
from graftcache.errors import BackboneError

#: Slack on the pixel bounds that pin the processor's resize to a grid (smart_resize's floor/ceil of a ratio).
BOUND_SLACK = 1.01


def image_grid(shape: tuple[int, int], image_processor, vision) -> tuple[int, int]:
    """The merged grid Wall-X gives a frame of `shape`: its own resize (256 px, multiples of 28), then the image
    processor's pixel bounds."""
    from lerobot.policies.wall_x.modeling_wall_x import _wall_x_resize_dimensions

    _, _, height, width = _wall_x_resize_dimensions(*shape)
    size = image_processor.size
    return merged_grid((height, width), vision.patch_size, vision.spatial_merge_size, size["shortest_edge"],
                       size["longest_edge"])


@contextlib.contextmanager
def pixel_bounds(image_processor, pixels: int) -> Iterator[None]:
    """The image processor's pixel bounds pinned around `pixels` for the block."""
    with patched(image_processor, size={"shortest_edge": int(pixels / BOUND_SLACK),
                                        "longest_edge": int(pixels * BOUND_SLACK)}):
        yield


class WallXAdapter(TowerReads, WrappedActivationCheckpointing, FlowLoss, BackboneAdapter):
    name = "wall_x"
    spec = SPEC

    def _patch_graft(self, graft) -> None:
        """Grafted, the ViT's forward projects the cached features (undone by reset)."""
        graft.shadow(self._vision_owner, "forward", self._visual_forward)

    # ------------------------------------------------------------------------------ construction
    @classmethod
    def _base_folder(cls, config, marker: dict | None) -> Path:
        """Wall-X's base config and processor folder `pretrained_name_or_path` names
        (graftcache.backbones.base.vlm_folder)."""
        return vlm_folder(config.pretrained_name_or_path, marker, WALLX_DIR, "Wall-X's base config and processor")

    @classmethod
    def _construct(cls, config, marker: dict | None) -> nn.Module:
        """WallXPolicy with its model built from the base folder's config and processor, no base weights read (the
        checkpoint holds the policy's; FAST mode, whose action tokenizer is hub-only, is refused in one line). Built
        on the meta device the LM head comes out untied: tied again."""
        policy = construct(config, cls._base_folder(config, marker))
        policy.model.tie_weights()
        return policy

    @classmethod
    def _checkpoint_keys(cls, policy: nn.Module, file_keys: Iterable[str]) -> dict[str, str]:
        """The LM head is tied to the word embedding; safetensors keeps one of the two names: read the other
        from it."""
        return tied_head_keys(file_keys, "model.lm_head.weight", "model.model.embed_tokens.weight")

    @classmethod
    def _make_processors(cls, config, stats: dict, marker: dict | None):
        from lerobot.policies.wall_x.processor_wall_x import make_wall_x_pre_post_processors

        return make_wall_x_pre_post_processors(config, dataset_stats=stats)

    # ------------------------------------------------------------------------------ geometry
    @property
    def _vision_owner(self) -> nn.Module:
        return self.policy.model.visual  # Qwen2_5_VisionTransformerPretrainedModel

    @property
    def _image_processor(self):
        return self.policy.model.processor.image_processor

    @staticmethod
    def _frame_shape(config) -> tuple[int, int]:
        cameras = list(config.image_features.values())
        if not cameras:
            raise BackboneError("wall_x config declares no camera")
        return tuple(cameras[0].shape[-2:])

    @classmethod
    def _grid_of_config(cls, config, marker: dict | None) -> tuple[int, int]:
        """The merged grid of the first camera's frame (the dataset's size, as the config declares it), through
        the base folder's processor."""
        from lerobot.policies.wall_x.qwen_model import Qwen2_5_VLConfig

        folder = cls._base_folder(config, marker)
        vision = Qwen2_5_VLConfig.from_pretrained(folder).vision_config
        return image_grid(cls._frame_shape(config), load_processor(folder).image_processor, vision)

    @functools.cached_property
    def token_grid(self) -> tuple[int, int]:
        return image_grid(self._frame_shape(self.config), self._image_processor, self._vision_owner.config)

    @property
    def num_steps(self) -> int:
        """Wall-X's Euler steps: `predict`'s default (lerobot's policy never passes another)."""
        from lerobot.policies.wall_x.modeling_wall_x import Qwen2_5_VLMoEForAction

        return inspect.signature(Qwen2_5_VLMoEForAction.predict).parameters["num_inference_timesteps"].default

    # ------------------------------------------------------------------------------ images
    def _visual_forward(self, own, visual: nn.Module, hidden_states: torch.Tensor, grid_thw=None, **kwargs):
        """The ViT's forward, or grafted: the cached features [images x tokens, C] through the pass-through and
        the projector (`pooler_output`, what Wall-X scatters into the image pads). The projector sees them a sample
        a row, [B, cameras x tokens, C]: a fused projector (graftcache.graft.FusedProjector) routes rows."""
        if not self.grafted:
            return own(visual, hidden_states, grid_thw, **kwargs)
        tokens = projected_rows(*self._tower_and_connector(), hidden_states, len(grid_thw),
                                len(self.config.image_features))
        return BaseModelOutputWithPooling(last_hidden_state=hidden_states, pooler_output=tokens)

    def _vision(self, images: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """[B, 3, H, W] in [0, 1] through the policy's own resize, processor and ViT."""
        from lerobot.policies.wall_x.modeling_wall_x import _resize_wall_x_image_batch

        self._check_native(images)
        resized, _ = _resize_wall_x_image_batch(images.clamp(0, 1))
        inputs = self._image_processor(images=list(resized), return_tensors="pt", device=resized.device)
        return vit_outputs(self._vision_owner, inputs["pixel_values"], inputs["image_grid_thw"])

    def _feature_images(self, batch: Mapping[str, Any], *, compute_position_ids: bool = False):
        """Grafted stand-in for WallXPolicy.preprocess_inputs: lerobot's own on blank frames whose processed grid
        is the cached features' (the processor's pixel bounds pinned to it for the call), with `pixel_values`
        then the cached features of every image, sample after sample, camera after camera."""
        images, _ = super()._feature_images(batch)
        counts = {f.shape[1] for f in images}
        if len(counts) != 1:
            raise BackboneError(f"{self.name}: cameras carry different token counts ({sorted(counts)})")
        gh, gw = prompt_grid(self.name, "Wall-X", self.token_grid, counts.pop())
        blank = dict(batch)
        size = batch[STATE].shape[0]
        for key in self.config.image_features:
            blank[key] = torch.zeros(size, 3, *self._frame_shape(self.config), device=batch[STATE].device)
        factor = self._vision_owner.config.patch_size * self._vision_owner.spatial_merge_size
        with pixel_bounds(self._image_processor, gh * gw * factor * factor):
            inputs = type(self.policy).preprocess_inputs(self.policy, blank, compute_position_ids=compute_position_ids)
        m = self._vision_owner.spatial_merge_size
        if inputs["image_grid_thw"].tolist() != [[1, gh * m, gw * m]] * len(inputs["image_grid_thw"]):
            raise BackboneError(f"{self.name}: the processor made grids {inputs['image_grid_thw'].tolist()} for the "
                                f"cached {gh}x{gw} tokens per camera")
        inputs["pixel_values"] = torch.stack(images, dim=1).flatten(0, 2)
        return inputs

    # ----------------------------------------------------------------------------- policy loss
    def sample_time(self, batch_size: int) -> torch.Tensor:
        """Wall-X's own draw, as a noise level (graftcache's convention: 1 - its t)."""
        return self.noise_level(self.policy.model.action_preprocessor.sample_time(batch_size, self.device))

    def _flow_losses(self, batch: Mapping[str, Any], noise: torch.Tensor, time: torch.Tensor) -> torch.Tensor:
        """lerobot's Wall-X forward with the given draws; the per-element loss from the action head's prediction
        and flow target (lerobot reduces the loss to a scalar)."""
        from lerobot.policies.wall_x import modeling_wall_x

        head = self.policy.model.action_preprocessor
        seen: dict[str, torch.Tensor] = {}
        hooks = [head.register_forward_hook(lambda m, args, out: seen.update(flow=out[1])),
                 head.action_proj_back.register_forward_hook(lambda m, args, out: seen.update(pred=out))]
        try:
            with shadowed(head, sample_time=lambda size, device: (1 - time).to(device, torch.float32)), \
                    given_noise(modeling_wall_x, noise, self.name, draws=("randn_like",)):
                self.policy.forward(dict(batch))
        finally:
            for hook in hooks:
                hook.remove()
        flow = seen["flow"]
        return (seen["pred"].view(flow.shape) - flow) ** 2

    @torch.no_grad()
    def _predict_chunk(self, batch: Mapping[str, Any], noise: torch.Tensor, num_steps: int) -> torch.Tensor:
        """`WallXPolicy.predict_action_chunk` from `noise` with `num_steps` Euler steps."""
        from lerobot.policies.wall_x import modeling_wall_x

        model = self.policy.model
        predict = functools.partial(type(model).predict, model, num_inference_timesteps=int(num_steps))
        with shadowed(model, predict=predict), given_noise(modeling_wall_x, noise, self.name, draws=("randn",)):
            return self.policy.predict_action_chunk(dict(batch))

    def _recompute_slots(self) -> Iterator[tuple[nn.Module, str]]:
        """Every decoder layer of the MoE language model (attention and both experts)."""
        for layer in self.policy.model.model.layers:
            yield layer, "forward"
