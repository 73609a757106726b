"""Tiny and released VLA-JEPA configurations (lerobot 0.6 `VLAJEPAConfig`: Qwen3-VL + a DiT flow head), buildable
offline.

lerobot's `Qwen3VLInterface` builds its VLM with `Qwen3VLForConditionalGeneration.from_pretrained(qwen_model_name)`
(weights and all, from the hub) and its processor with `AutoProcessor.from_pretrained(qwen_model_name)`. `construct`
rebinds the first name in lerobot's qwen_interface module, for the time of the constructor, to a loader that
builds the model from the folder's config.json alone (`_from_config`: the policy checkpoint holds the weights),
so a Qwen folder - the tiny one shipped under graftcache/resources/tiny/qwen3_vl/, or Qwen/Qwen3-VL-2B-Instruct's
snapshot in the HF cache - is read through one code path. The tiny folder is generated once by
`python -m graftcache.backbones.vla_jepa.tiny` (like tiny_assets.py's): a byte-level BPE tokenizer with Qwen's chat
and vision tokens, Qwen3-VL's chat template (no default system turn), Qwen2-VL's image processor at Qwen3-VL's
patch 16 / merge 2 / mean-std 0.5, and the tiny Qwen3-VL config.

The world model (V-JEPA2 encoder `jepa_encoder_name` + `ActionConditionedVideoPredictor`) is a training-only
auxiliary loss on future video frames; inference never runs it. `construct` builds the policy with
`enable_world_model=False`: the prompt is the same (its action-token count comes from `jepa_tubelet_size`, which
must match the encoder's), the world-model weights of a checkpoint are simply not read.

- tiny: vision 32 wide x 2 blocks (deepstack after block 0, as the released tower injects three), merger into a
  Qwen3 text model 64 wide x 2 layers (4 heads, 2 KV heads, vocabulary 1088 >= the tokenizer's 773 + 41 action
  tokens); DiT-test action head (2 heads x 8) x 2 layers; pixels bounded to 4..16 x 32*32, so a 128 px frame ->
  8x8 patches -> 2x2 merge -> 4x4 = 16 tokens per camera.
- released (lerobot/VLA-JEPA-LIBERO on Qwen/Qwen3-VL-2B-Instruct): vision 1024 wide x 24 blocks (deepstack after
  5, 11, 17), merger into the 2048-wide, 28-layer text model; Qwen3-VL's processor bounds (65536 .. 16777216
  pixels): 256 px -> 16x16 patches -> 8x8 = 64 tokens per camera; DiT-B x 16 layers; lerobot's defaults otherwise.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from pathlib import Path

import torch

from graftcache.backbones.patching import patched
from graftcache.backbones.tiny import TinyBuild, action_features, build_seeded, print_written, visual_features
from graftcache.backbones.tiny_assets import QWEN3_VL_DIR, write_qwen3_vl

TINY_IMAGE_SIZE = 128  # what train-tiny resizes frames to (requests.TinyTrainConfig.image_size)
#: Qwen/Qwen3-VL-2B-Instruct's config.json (the fields that set the geometry; the rest are transformers' defaults).
QWEN3_VL_2B = {
    "vision_config": {"depth": 24, "hidden_size": 1024, "intermediate_size": 4096, "num_heads": 16, "in_channels": 3,
                      "out_hidden_size": 2048, "patch_size": 16, "spatial_merge_size": 2, "temporal_patch_size": 2,
                      "num_position_embeddings": 2304, "deepstack_visual_indexes": [5, 11, 17],
                      "hidden_act": "gelu_pytorch_tanh"},
    "text_config": {"hidden_size": 2048, "intermediate_size": 6144, "num_hidden_layers": 28,
                    "num_attention_heads": 16, "num_key_value_heads": 8, "head_dim": 128, "vocab_size": 151936,
                    "max_position_embeddings": 262144, "tie_word_embeddings": True, "dtype": "bfloat16",
                    "rope_parameters": {"rope_type": "default", "mrope_section": [24, 20, 20],
                                        "mrope_interleaved": True, "rope_theta": 5000000.0}},
    "tie_word_embeddings": True, "dtype": "bfloat16", "image_token_id": 151655, "video_token_id": 151656,
    "vision_start_token_id": 151652, "vision_end_token_id": 151653,
}


@contextlib.contextmanager
def qwen_from_config(qwen_config=None) -> Iterator[None]:
    """lerobot's `Qwen3VLInterface` with its VLM built from a config instead of downloaded weights: from
    `qwen_config` when given, else from the config.json of the folder it names."""
    from lerobot.policies.vla_jepa import qwen_interface

    real = qwen_interface.Qwen3VLForConditionalGeneration

    class FromConfig:
        @staticmethod
        def from_pretrained(name: str, torch_dtype: torch.dtype | None = None, **_: object):
            from transformers import AutoConfig

            config = qwen_config if qwen_config is not None else AutoConfig.from_pretrained(name)
            return real._from_config(config, dtype=torch_dtype)

    with patched(qwen_interface, Qwen3VLForConditionalGeneration=FromConfig):
        yield


def construct(config, folder: Path, qwen_config=None):
    """VLAJEPAPolicy(config) without its world model, its Qwen3-VL built from `qwen_config` or `folder`'s config
    and its processor read from `folder` (the config keeps the Qwen name it had)."""
    from lerobot.policies.vla_jepa.modeling_vla_jepa import VLAJEPAPolicy

    config.enable_world_model = False
    with patched(config, qwen_model_name=str(folder)), qwen_from_config(qwen_config):
        return VLAJEPAPolicy(config)


def _config(tiny: TinyBuild, image_size: int, qwen: str, device: str, **kwargs):
    from lerobot.policies.vla_jepa.configuration_vla_jepa import VLAJEPAConfig

    return VLAJEPAConfig(qwen_model_name=qwen, enable_world_model=False, device=device,
                         input_features=visual_features(tiny, image_size), output_features=action_features(tiny),
                         action_dim=tiny.action_dim, state_dim=tiny.state_dim, **kwargs)


def vla_jepa_tiny_config(tiny: TinyBuild, device: str, image_size: int = TINY_IMAGE_SIZE):
    """Tiny VLA-JEPA at the dataset's `image_size` (the tiny processor bounds it to 4x4 merged tokens)."""
    return _config(tiny, image_size, str(QWEN3_VL_DIR), device, torch_dtype="float32", action_model_type="DiT-test",
                   action_num_layers=2, action_hidden_size=32, action_dropout=0.0,
                   num_embodied_action_tokens_per_instruction=4, num_action_tokens_per_timestep=2,
                   chunk_size=tiny.chunk_size, n_action_steps=tiny.chunk_size, num_inference_timesteps=tiny.num_steps)


def vla_jepa_released_config(cameras: tuple[str, ...], image_size: int, state_dim: int, action_dim: int,
                             device: str):
    """lerobot/VLA-JEPA-LIBERO's geometry for a dataset: Qwen/Qwen3-VL-2B-Instruct, DiT-B x 16 layers, chunk 7,
    32 embodied-action tokens, 4 denoising steps (lerobot's defaults, which the port set from the checkpoints)."""
    tiny = TinyBuild(cameras=cameras, state_dim=state_dim, action_dim=action_dim)
    return _config(tiny, image_size, "Qwen/Qwen3-VL-2B-Instruct", device)


def build_tiny(tiny: TinyBuild, stats: dict | None, device: str):
    """Random-init tiny VLA-JEPA, its Qwen3-VL from the shipped tiny folder, and its processors
    (graftcache.backbones.tiny.build_seeded)."""
    from lerobot.policies.vla_jepa.processor_vla_jepa import make_vla_jepa_pre_post_processors

    return build_seeded(tiny, stats, device, vla_jepa_tiny_config(tiny, device),
                        lambda config: construct(config, QWEN3_VL_DIR), make_vla_jepa_pre_post_processors)


if __name__ == "__main__":
    print_written(write_qwen3_vl())
