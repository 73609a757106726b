"""Tiny GR00T N1.7 configuration (lerobot 0.6 `GrootConfig` + `GR00TN17`), buildable offline; the construction it
shares with the released policy is graftcache/backbones/groot/construct.py.

A lerobot GR00T checkpoint keeps only `GrootConfig`; its model is rebuilt by `GR00TN17.from_pretrained(
base_model_path)`, which downloads the base checkpoint (its `GR00TN17Config` and weights). The backbone inside
comes from `Qwen3Backbone._from_backbone_config(model_name)`: lerobot's hard-coded copy of
nvidia/Cosmos-Reason2-2B's Qwen3-VL config for that name, `AutoConfig.from_pretrained(model_name)` for any other;
the processor step loads the tokenizer, image and video processors from the same `model_name`. So:

- `graftcache.backbones.groot.construct.construct` builds the policy from a `GR00TN17Config` without any weights,
  here the tiny one below;
- the tiny Cosmos-Reason2 stand-in is graftcache/resources/tiny/groot/ (generated once by
  `python -m graftcache.backbones.groot.tiny`, like tiny_assets.py's folders): the tiny Qwen3-VL config.json,
  a byte-level BPE tokenizer with Qwen's chat tokens and a Qwen3-VL style chat template (no default system
  message), Qwen2-VL's image processor at Qwen3-VL's settings (patch 16, merge 2, temporal patch 2, mean/std 0.5)
  and Qwen3-VL's video processor. It is `model_name` of the tiny base config, so the backbone and the processor
  come from it through the code path a real folder takes.

- tiny: Qwen3-VL vision 32 wide x 2 blocks (one deepstack merger, after block 0), merger into a Qwen3 text model
  64 wide x 3 layers, cut at layer 2 (GR00T's `select_layer`); GR00T's VLM step resizes every frame to 128 px
  (crop 115/128, GR00T's 230/256 ratio), the processor keeps it: 8x8 patches -> 2x2 merge -> 4x4 = 16 tokens per
  camera; action head: state/action encoders 32/48 wide, an alternate-VL DiT 4 blocks x 2 heads x 24, one
  VL self-attention layer, action horizon = the chunk.
- released (nvidia/GR00T-N1.7-3B, lerobot's `GR00T_N1_7_DEFAULTS` and hard-coded Cosmos-Reason2-2B config):
  vision 1024 wide x 24 blocks, merger into a 2048-wide Qwen3 LM of 28 layers cut at 16; frames resized to
  256 px, patch 16 x merge 2 -> 8x8 = 64 tokens per camera (Qwen3-VL-2B's processor keeps 256x256: its pixel
  bounds are 65536 .. 16777216).
"""

from __future__ import annotations

import functools

from graftcache.backbones.groot.construct import construct
from graftcache.backbones.tiny import TinyBuild, action_features, build_seeded, print_written, visual_features
from graftcache.backbones.tiny_assets import TINY_ROOT, write_qwen3_vl

GROOT_DIR = TINY_ROOT / "groot"
TINY_TARGET = 128            # GR00T's VLM step resizes every frame to this (released: 256)
TINY_CROP = 115              # centre crop before the resize, GR00T's 230/256 ratio
#: The tiny Cosmos-Reason2 stand-in is the tiny Qwen3-VL with a third text layer, so that GR00T's `select_layer` (2)
#: cuts the LM as the released one cuts 28 layers at 16.
GROOT_TEXT = {"num_hidden_layers": 3, "max_position_embeddings": 4096}
#: GR00TN17Config overrides of the tiny base model (the rest: lerobot's GR00T_N1_7_DEFAULTS).
TINY_GROOT = {
    "backbone_embedding_dim": 64, "select_layer": 2, "hidden_size": 32, "input_embedding_dim": 48,
    "max_seq_len": 64, "max_num_embodiments": 32, "num_inference_timesteps": 4,
    "diffusion_model_cfg": {"positional_embeddings": None, "num_layers": 4, "num_attention_heads": 2,
                            "attention_head_dim": 24, "norm_type": "ada_norm", "dropout": 0.0,
                            "final_dropout": True, "output_dim": 32, "interleave_self_attention": True},
    "vl_self_attention_cfg": {"positional_embeddings": None, "num_layers": 1, "num_attention_heads": 2,
                              "attention_head_dim": 32, "dropout": 0.0, "final_dropout": True},
    "dtype": "float32", "model_dtype": "float32",
}


def tiny_base_config():
    """The tiny GR00TN17Config: its backbone is the shipped tiny Qwen3-VL folder."""
    from lerobot.policies.groot.groot_n1_7 import GR00TN17Config

    return GR00TN17Config(model_name=str(GROOT_DIR), **TINY_GROOT)


def groot_tiny_config(tiny: TinyBuild, device: str, image_size: int = TINY_TARGET):
    """Tiny GrootConfig at the dataset's `image_size` (GR00T's VLM step resizes frames to TINY_TARGET)."""
    from lerobot.policies.groot.configuration_groot import GrootConfig

    dims = max(tiny.state_dim, tiny.action_dim, 8)
    return GrootConfig(base_model_path=str(GROOT_DIR), device=device, chunk_size=tiny.chunk_size,
                       n_action_steps=tiny.chunk_size, max_state_dim=dims, max_action_dim=dims,
                       num_inference_timesteps=tiny.num_steps, use_bf16=False,
                       input_features=visual_features(tiny, image_size), output_features=action_features(tiny))


def tiny_base_for(config):
    """The tiny base model at a tiny GrootConfig's sizes (the action head's widths follow the padded dims)."""
    base = tiny_base_config()
    base.max_state_dim, base.max_action_dim = config.max_state_dim, config.max_action_dim
    base.action_horizon = config.chunk_size
    return base


@functools.cache
def vlm_step_name() -> str:
    """Registry name of GR00T's Qwen3-VL prompt step (the processor override key)."""
    from lerobot.policies.groot.processor_groot import GrootN17VLMEncodeStep

    return GrootN17VLMEncodeStep._registry_name


def tiny_image_geometry(pre) -> None:
    """GR00T's VLM step at the tiny frame size (what a tiny checkpoint's saved preprocessor keeps)."""
    for step in pre.steps:
        if type(step).__name__ == "GrootN17VLMEncodeStep":
            step.model_name = str(GROOT_DIR)
            step.image_target_size, step.image_crop_size = [TINY_TARGET] * 2, [TINY_CROP] * 2


def build_tiny(tiny: TinyBuild, stats: dict | None, device: str):
    """Random-init tiny GR00T on the tiny base model and its processors (graftcache.backbones.tiny.build_seeded),
    the VLM step at the tiny frame size."""
    from lerobot.policies.groot.processor_groot import make_groot_pre_post_processors

    policy, pre, post, geometry = build_seeded(tiny, stats, device, groot_tiny_config(tiny, device),
                                               lambda config: construct(config, tiny_base_for(config)),
                                               make_groot_pre_post_processors)
    tiny_image_geometry(pre)
    return policy, pre, post, geometry


if __name__ == "__main__":
    print_written(write_qwen3_vl(GROOT_DIR, GROOT_TEXT))
