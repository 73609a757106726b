"""GR00T N1.7 (lerobot 0.6: Cosmos-Reason2-2B's Qwen3-VL cut at LM layer 16 + a DiT flow head) as a graftable backbone.

Vision path (processor_groot.py, groot_n1_7.py; transformers qwen3_vl): the preprocessor packs the cameras
(sorted by key unless the checkpoint names its video keys) into one video, GR00T's VLM step resizes every frame
to its target size (256 px, after a 230/256 centre crop) and Qwen3-VL's processor cuts it into 16 px patches
ordered by 2x2 merge block, writing one `<|image_pad|>` per merged block into one user message (all frames, then
the task). In the model, `Qwen3VLModel.get_image_features` runs the ViT (`visual.blocks`) and its `merger`
(LayerNorm, 2x2 concat, MLP into the LM width), scatters the tokens into the image pads, camera after camera,
and adds three "deepstack" features (mergers of ViT blocks 5, 11, 17) to the first LM layers' hidden states at
those positions. The action head reads the LM's layer-16 states. Tokens per camera: 256 px -> 16x16 patches ->
8x8 = 64, whatever the dataset's frame size.

Graft slots: the image-pad positions, every camera. The tower (`visual.blocks`) becomes the pass-through and the
merger (the connector) the projector; Qwen's `get_image_features` is shadowed on the instance so that, grafted, it
projects the cached features instead of running the ViT (unchanged otherwise). Deepstack features come out of
the native ViT's inner blocks, so a grafted encoder has none: grafted, none are added (the native control's
ViT is likewise a cached tower, so its deepstack is absent too). The prompt is the policy's own, built by its
processor steps from blank frames sized so that they give the cached grid (the prompt depends on the frame size
only, never on the pixels), so the pad positions, M-RoPE positions and masks are exactly the policy's.

GR00T draws its flow time (`sample_time`) and noise (`torch.randn` in groot_n1_7.py) inside `forward` and
`get_action`; `loss` and `predict` run lerobot's own code with the time sampler shadowed and that module's
`torch.randn` answering with the given noise, and `loss` reads the velocity from the action decoder's output.
GR00T's time runs the other way from the pi0 family's that `fit` draws (graftcache.fit.loop.flow_time: 1 is pure
noise there, the action here; GR00T samples (1 - Beta(1.5, 1)) * 0.999, the mirror of lerobot's pi0 draw), so a
given time t is GR00T's 1 - t: the same draw means the same noise level on every backbone.
"""

from __future__ import annotations

import contextlib
import functools
from collections.abc import Iterator, Mapping
from typing import Any

import torch
from torch import nn

from graftcache.backbones.base import BackboneAdapter
from graftcache.backbones.batches import ACTION, STATE
from graftcache.backbones.checkpoint import cached_repo
from graftcache.backbones.given_draws import given_noise, shadowed
from graftcache.backbones.groot.construct import base_config, construct
from graftcache.backbones.groot.spec import SPEC, VLM_STEP
from graftcache.backbones.groot.tiny import (
    GROOT_DIR,
    TINY_TARGET,
    tiny_base_for,
    tiny_image_geometry,
    vlm_step_name,
)
from graftcache.backbones.patching import patched
from graftcache.backbones.policy_loss import FlowLoss
from graftcache.backbones.qwen_vl import (
    TowerReads,
    cached_token_count,
    check_slots,
    image_token_counts,
    merged_grid,
    prompt_grid,
    qwen3_vl_image_features,
    raster_patches,
)
from graftcache.backbones.tiny_assets import QWEN3_VL_MERGE, QWEN3_VL_PATCH, QWEN3_VL_PIXELS, TINY_QWEN3_VL_PIXELS
from graftcache.errors import BackboneError
from graftcache.graft import feature_key

PACK_STEP = "GrootN17PackInputsStep"
#: The normalised action chunk as GR00T's pack step pads it to `max_action_dim` (what its forward reads); the
#: prepared batch's `action` is the chunk at the dataset's action width, like every other backbone's.
PADDED_ACTION = "groot_padded_action"


class GrootAdapter(TowerReads, FlowLoss, BackboneAdapter):
    name = "groot"
    spec = SPEC

    def _patch_graft(self, graft) -> None:
        """Grafted, Qwen's `get_image_features` projects the cached features (undone by reset)."""
        graft.shadow(self._qwen, "get_image_features", self._image_features)

    # ------------------------------------------------------------------------------ construction
    @classmethod
    def _configure(cls, folder, config, marker: dict | None) -> None:
        """A tiny checkpoint's base model is the shipped tiny folder (its saved path points into the package that
        saved it)."""
        if marker is not None:
            config.base_model_path = str(GROOT_DIR)

    @classmethod
    def _construct(cls, config, marker: dict | None) -> nn.Module:
        """GrootPolicy on its base model's config (the tiny one, or `base_model_path`'s config.json), no base
        weights read: the checkpoint holds them all."""
        return construct(config, tiny_base_for(config) if marker is not None else base_config(config.base_model_path))

    @classmethod
    def _vlm_folder(cls, marker: dict | None) -> str:
        """Where the Qwen3-VL tokenizer and processors come from: the tiny folder, or Cosmos-Reason2-2B (a local
        HF cache snapshot: lerobot's step names the hub id)."""
        from lerobot.policies.groot.configuration_groot import GROOT_N1_7_BACKBONE_MODEL

        if marker is not None:
            return str(GROOT_DIR)
        return str(cached_repo(GROOT_N1_7_BACKBONE_MODEL, "GR00T's Qwen3-VL processor"))

    @classmethod
    def _processor_overrides(cls, config, marker: dict | None, device: str) -> tuple[dict, dict]:
        pre, post = super()._processor_overrides(config, marker, device)
        pre[vlm_step_name()] = {"model_name": cls._vlm_folder(marker), "device": device}
        return pre, post

    @classmethod
    def _make_processors(cls, config, stats: dict, marker: dict | None):
        from lerobot.policies.groot.processor_groot import make_groot_pre_post_processors

        pre, post = make_groot_pre_post_processors(config, dataset_stats=stats)
        if marker is not None:
            tiny_image_geometry(pre)
        else:
            cls._step(pre, VLM_STEP).model_name = cls._vlm_folder(marker)
        return pre, post

    # ------------------------------------------------------------------------------ geometry
    @property
    def _groot(self) -> nn.Module:
        return self.policy._groot_model  # GR00TN17

    @property
    def _qwen(self) -> nn.Module:
        return self._groot.backbone.model.model  # Qwen3VLModel

    @property
    def _vision_owner(self) -> nn.Module:
        return self._qwen.visual  # Qwen3VLVisionModel

    @classmethod
    def _grid_of_config(cls, config, marker: dict | None) -> tuple[int, int]:
        """The merged grid of GR00T's frame: its VLM step's target size (the tiny one; a raw base checkpoint's
        processor_config.json; lerobot's N1.7 default 256 px) through Qwen3-VL's processor bounds."""
        from lerobot.policies.groot.configuration_groot import N1_7_DEFAULT_IMAGE_TARGET_SIZE
        from lerobot.policies.groot.processor_groot import _load_n1_7_checkpoint_processor_assets

        if marker is not None:
            return merged_grid((TINY_TARGET, TINY_TARGET), QWEN3_VL_PATCH, QWEN3_VL_MERGE, *TINY_QWEN3_VL_PIXELS)
        assets = _load_n1_7_checkpoint_processor_assets(config)
        target = assets.image_target_size if assets is not None and assets.image_target_size else None
        return merged_grid(tuple(target or N1_7_DEFAULT_IMAGE_TARGET_SIZE), QWEN3_VL_PATCH, QWEN3_VL_MERGE,
                           *QWEN3_VL_PIXELS)

    @property
    def chunk_size(self) -> int:
        """The action head's horizon (GR00T draws its noise at the model's `action_horizon`)."""
        return self._groot.config.action_horizon

    @property
    def num_steps(self) -> int:
        """GrootConfig's override, else the base model's `num_inference_timesteps`."""
        return self.config.num_inference_timesteps or self._groot.action_head.num_inference_timesteps

    # ------------------------------------------------------------------------------ images
    @staticmethod
    def _step(pipeline, name: str):
        steps = [s for s in pipeline.steps if type(s).__name__ == name]
        if not steps:
            raise BackboneError(f"groot: the preprocessor has no {name}")
        return steps[0]

    @functools.cached_property
    def _vlm_step(self):
        return self._step(self.preprocessor, VLM_STEP)

    @functools.cached_property
    def _view_keys(self) -> list[str]:
        """The cameras in the order GR00T's pack step puts them into its video (and so into the prompt)."""
        return self._step(self.preprocessor, PACK_STEP)._ordered_image_keys({k: None for k in self.camera_keys})

    def _image_features(self, own, qwen: nn.Module, pixel_values: torch.Tensor, image_grid_thw=None, **kwargs):
        """Qwen's `get_image_features`, or grafted: the cached features of every view (one image each) through the
        pass-through and the projector, and no deepstack features (GR00T's "none" is None)."""
        if not self.grafted:
            return own(qwen, pixel_values, image_grid_thw, **kwargs)
        return qwen3_vl_image_features(*self._tower_and_connector(), qwen, pixel_values, image_grid_thw,
                                       len(self._view_keys), deepstack=None)

    def _vision(self, images: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """[B, 3, H, W] in [0, 1] through GR00T's own frame transform, Qwen3-VL's processor and ViT: (pre-merger
        patch grid [B, gh, gw, C] in raster order, post-merger tokens [B, T, D])."""
        from lerobot.policies.groot.processor_groot import _to_uint8_np_bthwc

        self._check_native(images)
        step, size = self._vlm_step, len(images)
        video = _to_uint8_np_bthwc(images.cpu())[:, :, None]  # (B, T=1, V=1, H, W, C), as the pack step makes it
        frames = [f for sample in step._build_sample_images(video, size, None) for f in sample]
        inputs = step.proc.image_processor(images=frames, return_tensors="pt")
        visual = self._vision_owner
        thw = inputs["image_grid_thw"].to(self.device)
        out = visual(inputs["pixel_values"].to(self.device, visual.dtype), grid_thw=thw)
        m = visual.spatial_merge_size
        _, gh, gw = thw[0].tolist()
        grid = raster_patches(out.last_hidden_state, size, gh, gw, m)
        tokens = out.pooler_output.view(size, (gh // m) * (gw // m), -1)
        return grid.float(), tokens.float()

    def _feature_images(self, batch: Mapping[str, Any], include_action: bool) -> dict[str, Any]:
        """Grafted stand-in for GrootPolicy._filter_groot_inputs: Qwen's `pixel_values` are the cached features of
        every image, sample after sample, camera after camera in the video's order (the image pads' order)."""
        from lerobot.policies.groot.modeling_groot import GrootPolicy

        feats = [batch.get(feature_key(k)) for k in self._view_keys]
        if any(f is None for f in feats):
            raise BackboneError(f"{self.name} batch has no features for camera(s) "
                                f"{[k for k, f in zip(self._view_keys, feats) if f is None]}")
        check_slots(self.name, {f.shape[1] for f in feats},
                    set(image_token_counts(batch["image_grid_thw"], self._vision_owner.spatial_merge_size)))
        inputs = GrootPolicy._filter_groot_inputs(self.policy, batch, include_action=include_action)
        inputs["pixel_values"] = torch.stack(feats, dim=1).flatten(0, 2)
        return inputs

    @contextlib.contextmanager
    def _frames_of_grid(self, gh: int, gw: int) -> Iterator[tuple[int, int]]:
        """GR00T's VLM step and Qwen's processor set, for the block, to keep a (gh*32, gw*32) frame as it is (no
        crop, that target size, pixel bounds of exactly that frame): yields the frame size."""
        step = self._vlm_step
        image = step.proc.image_processor
        h, w = gh * QWEN3_VL_PATCH * QWEN3_VL_MERGE, gw * QWEN3_VL_PATCH * QWEN3_VL_MERGE
        fields = ("image_target_size", "image_crop_size", "crop_fraction", "shortest_image_edge")
        with patched(step, **dict(zip(fields, ([h, w], None, None, None)))), \
                patched(image, size={"shortest_edge": h * w, "longest_edge": h * w}):
            yield h, w

    def prepare(self, raw: Mapping[str, Any]) -> dict[str, Any]:
        """lerobot's preprocessor (packing, normalisation, prompt). Grafted, the prompt is made from blank frames
        whose processed grid is the cached features' (the token grid, or a pooling control's square grid), and
        the features ride along for `_feature_images`."""
        if not self.grafted:
            return self._unpadded(super().prepare(raw))
        batch = dict(raw)
        tokens = cached_token_count(self.name, batch, self.camera_keys)
        with self._frames_of_grid(*prompt_grid(self.name, "GR00T", self.token_grid, tokens)) as (h, w):
            size = batch[STATE].shape[0]
            for key in self.camera_keys:
                batch[key] = torch.zeros(size, 3, h, w)
            out = self.preprocessor(batch)
        for key in self.camera_keys:
            out.pop(key, None)
        return self._unpadded(out)

    def _unpadded(self, batch: dict[str, Any]) -> dict[str, Any]:
        """`action` cut back to the dataset's width (the scored target), the padded chunk kept for GR00T; a batch
        without actions (a policy acting: graftcache.export) comes back from the preprocessor with `action` None."""
        if batch.get(ACTION) is not None:
            batch[PADDED_ACTION] = batch[ACTION]
            batch[ACTION] = batch[ACTION][..., : self.action_dim]
        return batch

    # ----------------------------------------------------------------------------- policy loss
    def sample_time(self, batch_size: int) -> torch.Tensor:
        """GR00T's own Beta sampler, as a noise level (1 = pure noise)."""
        return self.noise_level(self._groot.action_head.sample_time(batch_size, self.device, torch.float32))

    def _flow_losses(self, batch: Mapping[str, Any], noise: torch.Tensor, time: torch.Tensor) -> torch.Tensor:
        """lerobot's GR00T forward with the given draws (`time` 1 = pure noise, GR00T's 1 - time); the per-element
        loss from the action decoder's output (GR00T's velocity is action - noise)."""
        from lerobot.policies.groot import groot_n1_7

        head = self._groot.action_head
        own = 1 - time
        decoded = []
        hook = head.action_decoder.register_forward_hook(lambda m, args, out: decoded.append(out))
        try:
            with given_noise(groot_n1_7, noise, self.name), self._callers_autocast(), \
                    shadowed(head, sample_time=lambda size, device, dtype: own.to(device, dtype)):
                self.policy.forward({**batch, ACTION: batch[PADDED_ACTION]})
        finally:
            hook.remove()
        action = batch[PADDED_ACTION].to(noise.dtype)
        velocity = action - noise
        return (decoded[0][:, -action.shape[1]:].to(velocity.dtype) - velocity) ** 2

    @torch.no_grad()
    def _predict_chunk(self, batch: Mapping[str, Any], noise: torch.Tensor, num_steps: int) -> torch.Tensor:
        """`GrootPolicy.predict_action_chunk` from `noise` with `num_steps` Euler steps."""
        from lerobot.policies.groot import groot_n1_7

        with patched(self._groot.action_head, num_inference_timesteps=int(num_steps)), \
                given_noise(groot_n1_7, noise, self.name), self._callers_autocast():
            return self.policy.predict_action_chunk(dict(batch))

    @contextlib.contextmanager
    def _callers_autocast(self) -> Iterator[None]:
        """GR00T's forward and get_action run in `autocast(bf16, enabled=config.use_bf16)`: on (public configs),
        bf16 whatever --compute-dtype says; off (the tiny config), graftcache's own bf16 autocast turned off, fp32.
        Meanwhile `use_bf16` says what the caller's autocast is, so the dtype rows record is the one that runs."""
        kind = self.device.type
        bf16 = torch.is_autocast_enabled(kind) and torch.get_autocast_dtype(kind) == torch.bfloat16
        with patched(self.policy.config, use_bf16=bf16):
            yield
