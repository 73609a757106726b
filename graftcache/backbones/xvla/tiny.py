"""Tiny and released X-VLA configurations (lerobot 0.6 `XVLAConfig`), buildable offline.

X-VLA keeps its whole Florence-2 geometry in `XVLAConfig.florence_config` (saved in config.json), so a tiny
checkpoint needs no geometry in its marker: the folder's config rebuilds it.

- tiny: DaViT 4 stages (16/32/48/64 wide, one block each, strides 4-2-2-2) at 128 px -> 4x4 grid, projector
  to 64 = 1 + 16 tokens per camera; BART encoder 64 wide x 2 layers; soft-prompted transformer 64 wide x 2
  layers; "auto" action space (loss on the real action dims, padded to 8). Florence-2 without dropout or
  drop-path; lerobot's soft-prompted transformer keeps the Dropout(0.1) its code fixes (released and tiny alike),
  so the policy draws dropout masks in train mode (as fits run it). The tokenizer is graftcache's tiny
  PaliGemma-style one (771 tokens < the 1024-row vocabulary), standing in for facebook/bart-large.
- released (lerobot/xvla-base, X-VLA-0.9B): Florence-2-large: DaViT 256/512/1024/2048 wide, depths 1-1-9-1,
  projection 1024, BART-large encoder (1024 wide, 12 layers, vocabulary 51289), transformer 1024 x 24.
"""

from __future__ import annotations

from graftcache.backbones.tiny import TinyBuild, action_features, build_seeded, visual_features
from graftcache.backbones.tiny_assets import PALIGEMMA_DIR

TINY_IMAGE_SIZE = 128
TINY_FLORENCE = {
    "vision_config": {"depths": [1, 1, 1, 1], "embed_dim": [16, 32, 48, 64], "num_heads": [1, 2, 2, 4],
                      "num_groups": [1, 2, 2, 4], "window_size": 4, "projection_dim": 64, "drop_path_rate": 0.0},
    "text_config": {"model_type": "bart", "d_model": 64, "encoder_layers": 2, "decoder_layers": 1,
                    "encoder_attention_heads": 4, "decoder_attention_heads": 4, "encoder_ffn_dim": 128,
                    "decoder_ffn_dim": 128, "vocab_size": 1024, "max_position_embeddings": 256,
                    "dropout": 0.0, "attention_dropout": 0.0, "activation_dropout": 0.0,
                    "pad_token_id": 0, "bos_token_id": 2, "eos_token_id": 1},
    "pad_token_id": 0, "bos_token_id": 2, "eos_token_id": 1,
}
#: Florence-2-large as the X-VLA checkpoints' config.json declares it (2toINF/X-VLA-*, lerobot/xvla-base).
FLORENCE2_LARGE = {
    "vision_config": {"depths": [1, 1, 9, 1], "embed_dim": [256, 512, 1024, 2048], "num_heads": [8, 16, 32, 64],
                      "num_groups": [8, 16, 32, 64], "window_size": 12, "projection_dim": 1024},
    "text_config": {"model_type": "bart", "vocab_size": 51289, "d_model": 1024, "encoder_layers": 12,
                    "decoder_layers": 12, "encoder_attention_heads": 16, "decoder_attention_heads": 16,
                    "encoder_ffn_dim": 4096, "decoder_ffn_dim": 4096, "max_position_embeddings": 4096},
    "pad_token_id": 1, "bos_token_id": 0, "eos_token_id": 2,
}


def _mean_std():
    from lerobot.configs.types import NormalizationMode

    return {"VISUAL": NormalizationMode.IDENTITY, "STATE": NormalizationMode.MEAN_STD,
            "ACTION": NormalizationMode.MEAN_STD}


def xvla_tiny_config(tiny: TinyBuild, device: str):
    from lerobot.policies.xvla.configuration_xvla import XVLAConfig

    return XVLAConfig(
        florence_config=TINY_FLORENCE, tokenizer_name=str(PALIGEMMA_DIR), tokenizer_max_length=48,
        hidden_size=64, depth=2, num_heads=4, len_soft_prompts=4, num_domains=1, max_len_seq=256,
        action_mode="auto", max_action_dim=max(tiny.action_dim, 8), max_state_dim=max(tiny.state_dim, 8),
        chunk_size=tiny.chunk_size, n_action_steps=tiny.chunk_size, num_denoising_steps=tiny.num_steps,
        resize_imgs_with_padding=(TINY_IMAGE_SIZE, TINY_IMAGE_SIZE), normalization_mapping=_mean_std(),
        device=device, input_features=visual_features(tiny, TINY_IMAGE_SIZE), output_features=action_features(tiny),
    )


def xvla_released_config(cameras: tuple[str, ...], image_size: int, state_dim: int, action_dim: int, device: str):
    """lerobot/xvla-base's geometry for a dataset (X-VLA's LIBERO recipe: chunk 32, "auto" action space padded
    to 20, 10 denoising steps; the policy's other defaults are lerobot's)."""
    from lerobot.policies.xvla.configuration_xvla import XVLAConfig

    tiny = TinyBuild(cameras=cameras, state_dim=state_dim, action_dim=action_dim)
    return XVLAConfig(florence_config=FLORENCE2_LARGE, action_mode="auto", normalization_mapping=_mean_std(),
                      device=device, input_features=visual_features(tiny, image_size),
                      output_features=action_features(tiny))


def build_tiny(tiny: TinyBuild, stats: dict | None, device: str):
    """Random-init tiny X-VLA and its processors (graftcache.backbones.tiny.build_seeded)."""
    from lerobot.policies.xvla.modeling_xvla import XVLAPolicy
    from lerobot.policies.xvla.processor_xvla import make_xvla_pre_post_processors

    return build_seeded(tiny, stats, device, xvla_tiny_config(tiny, device), XVLAPolicy, make_xvla_pre_post_processors)
