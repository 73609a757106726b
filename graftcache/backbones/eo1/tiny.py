"""Tiny and released EO-1 configurations (lerobot 0.6 `EO1Config`: Qwen2.5-VL + a flow head), buildable offline.

EO-1 keeps its whole Qwen2.5-VL geometry in `EO1Config.vlm_config` (saved in config.json), so a tiny checkpoint
needs no geometry in its marker. Its processor step loads a `Qwen2_5_VLProcessor` from `vlm_base`; the tiny one
is shipped under graftcache/resources/tiny/qwen2_5_vl/ (generated once by `python -m graftcache.backbones.eo1.tiny`,
like tiny_assets.py's folders): a byte-level BPE tokenizer with Qwen's chat tokens and chat template, and
Qwen2-VL's image processor (patch 14, merge 2, temporal patch 2, CLIP mean/std).

- tiny: vision tower 32 wide x 2 blocks (window attention, the last block full), merger into a Qwen2.5 text
  model 64 wide x 2 layers (4 heads, 2 KV heads, vocabulary 1088 >= the tokenizer's 771 + EO-1's 7 added
  tokens); the processor bounds the pixels to 4..16 x 28*28, so a 128 px frame -> smart_resize 112x112 -> 8x8
  patches -> 2x2 merge -> 4x4 = 16 tokens per camera.
- released (lerobot/eo1-base = IPEC-COMMUNITY/EO-1-3B on Qwen/Qwen2.5-VL-3B-Instruct, EO-1's `vlm_base`):
  vision 1280 wide x 32 blocks, merger into a 2048-wide, 36-layer text model; 64*28*28 .. 128*28*28 pixels:
  256 px -> 252 -> 18x18 patches -> 9x9 = 81.
"""

from __future__ import annotations

from pathlib import Path

from graftcache.backbones.patching import patched
from graftcache.backbones.tiny import TinyBuild, action_features, build_seeded, print_written, visual_features
from graftcache.backbones.tiny_assets import (
    QWEN25_VL_3B,
    QWEN_VL_DIR,
    QWEN_VL_TINY_PIXELS,
    qwen25_vl_ids,
    write_qwen_vl,
)

TINY_IMAGE_SIZE = 128  # what train-tiny resizes frames to (requests.TinyTrainConfig.image_size)


def _config(tiny: TinyBuild, vlm_config: dict, vlm_base: str, image_size: int, pixels: tuple[int, int] | None,
            device: str):
    from lerobot.policies.eo1.configuration_eo1 import EO1Config

    kwargs = {} if pixels is None else {"image_min_pixels": pixels[0], "image_max_pixels": pixels[1]}
    return EO1Config(vlm_base=vlm_base, vlm_config=vlm_config, device=device,
                     input_features=visual_features(tiny, image_size), output_features=action_features(tiny),
                     **kwargs)


def eo1_tiny_config(tiny: TinyBuild, device: str, image_size: int = TINY_IMAGE_SIZE):
    """Tiny EO-1 at the dataset's `image_size` (the processor resizes to the tiny pixel bound)."""
    config = _config(tiny, qwen25_vl_ids(), str(QWEN_VL_DIR), image_size, (4 * 28 * 28, QWEN_VL_TINY_PIXELS), device)
    config.chunk_size = config.n_action_steps = tiny.chunk_size
    config.num_denoise_steps = tiny.num_steps
    config.max_state_dim, config.max_action_dim = max(tiny.state_dim, 8), max(tiny.action_dim, 8)
    config.dtype = "float32"
    config.attn_implementation = "sdpa"
    return config


def eo1_released_config(cameras: tuple[str, ...], image_size: int, state_dim: int, action_dim: int, device: str):
    """lerobot/eo1-base's geometry for a dataset (IPEC-COMMUNITY/EO-1-3B converted: Qwen/Qwen2.5-VL-3B-Instruct,
    chunk 16, state/action padded to 32, two action-projector layers, 10 denoising steps; lerobot's defaults
    otherwise)."""
    tiny = TinyBuild(cameras=cameras, state_dim=state_dim, action_dim=action_dim)
    config = _config(tiny, QWEN25_VL_3B, "Qwen/Qwen2.5-VL-3B-Instruct", image_size, None, device)
    config.chunk_size = 16
    return config


def construct(config):
    """EO1Policy(config) from the config alone: lerobot builds the VLM with `_from_config` when the config has a
    `pretrained_path` (a checkpoint's weights follow), else downloads `vlm_base`'s weights."""
    from lerobot.policies.eo1.modeling_eo1 import EO1Policy

    with patched(config, pretrained_path=config.pretrained_path or Path("graftcache-no-weights")):
        return EO1Policy(config)


def build_tiny(tiny: TinyBuild, stats: dict | None, device: str):
    """Random-init tiny EO-1 and its processors (graftcache.backbones.tiny.build_seeded)."""
    from lerobot.policies.eo1.processor_eo1 import make_eo1_pre_post_processors

    return build_seeded(tiny, stats, device, eo1_tiny_config(tiny, device), construct, make_eo1_pre_post_processors)


if __name__ == "__main__":
    print_written(write_qwen_vl())
