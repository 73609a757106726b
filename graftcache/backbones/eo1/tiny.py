"""Tiny and released EO-1 configurations (lerobot 0.6 `EO1Config`: Qwen2.5-VL + a flow head), buildable offline.

EO-1 keeps its whole Qwen2.5-VL geometry in `EO1Config.vlm_config` (saved in config.json), so a tiny checkpoint
needs no geometry in its marker. Its processor step loads a `Qwen2_5_VLProcessor` from `vlm_base`; the tiny one
is shipped under graftcache/resources/tiny/qwen2_5_vl/ (generated once by `python -m graftcache.backbones.tiny_eo1`,
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

from graftcache.backbones.tiny import TinySpec, _action_features, _require_stats, _visual_features, seeded_policy
from graftcache.backbones.tiny_assets import TINY_ROOT, qwen_tokenizer, qwen_vision_ids

QWEN_VL_DIR = TINY_ROOT / "qwen2_5_vl"
TINY_IMAGE_SIZE = 128  # what train-tiny resizes frames to (requests.TinyTrainConfig.image_size)
TINY_PIXELS = 16 * 28 * 28  # max pixels of the tiny processor: 112 x 112
#: Qwen2-VL's chat template (what Qwen/Qwen2.5-VL-3B-Instruct ships): images as vision_start/image_pad/vision_end.
CHAT_TEMPLATE = (
    "{% set image_count = namespace(value=0) %}{% set video_count = namespace(value=0) %}"
    "{% for message in messages %}{% if loop.first and message['role'] != 'system' %}<|im_start|>system\n"
    "You are a helpful assistant.<|im_end|>\n{% endif %}<|im_start|>{{ message['role'] }}\n"
    "{% if message['content'] is string %}{{ message['content'] }}<|im_end|>\n{% else %}"
    "{% for content in message['content'] %}"
    "{% if content['type'] == 'image' or 'image' in content or 'image_url' in content %}"
    "{% set image_count.value = image_count.value + 1 %}<|vision_start|><|image_pad|><|vision_end|>"
    "{% elif content['type'] == 'video' or 'video' in content %}"
    "{% set video_count.value = video_count.value + 1 %}<|vision_start|><|video_pad|><|vision_end|>"
    "{% elif 'text' in content %}{{ content['text'] }}{% endif %}{% endfor %}<|im_end|>\n{% endif %}"
    "{% endfor %}{% if add_generation_prompt %}<|im_start|>assistant\n{% endif %}"
)
TINY_QWEN = {
    "vision_config": {"depth": 2, "hidden_size": 32, "intermediate_size": 64, "num_heads": 2, "in_chans": 3,
                      "out_hidden_size": 64, "patch_size": 14, "spatial_merge_size": 2, "temporal_patch_size": 2,
                      "window_size": 56, "fullatt_block_indexes": [1]},
    "text_config": {"hidden_size": 64, "intermediate_size": 128, "num_hidden_layers": 2, "num_attention_heads": 4,
                    "num_key_value_heads": 2, "vocab_size": 1088, "max_position_embeddings": 1024,
                    "rope_parameters": {"rope_type": "default", "mrope_section": [2, 2, 4], "rope_theta": 10000.0},
                    "tie_word_embeddings": True},
    "tie_word_embeddings": True,
}
#: Qwen/Qwen2.5-VL-3B-Instruct's config.json (the fields that set the geometry; the rest are transformers' defaults).
QWEN25_VL_3B = {
    "vision_config": {"depth": 32, "hidden_size": 1280, "intermediate_size": 3420, "num_heads": 16, "in_chans": 3,
                      "out_hidden_size": 2048, "patch_size": 14, "spatial_merge_size": 2, "temporal_patch_size": 2,
                      "window_size": 112, "fullatt_block_indexes": [7, 15, 23, 31], "hidden_act": "silu"},
    "text_config": {"hidden_size": 2048, "intermediate_size": 11008, "num_hidden_layers": 36,
                    "num_attention_heads": 16, "num_key_value_heads": 2, "vocab_size": 151936,
                    "max_position_embeddings": 128000, "tie_word_embeddings": True,
                    "rope_parameters": {"rope_type": "default", "mrope_section": [16, 24, 24],
                                        "rope_theta": 1000000.0}},
    "tie_word_embeddings": True, "dtype": "bfloat16", "image_token_id": 151655, "video_token_id": 151656,
    "vision_start_token_id": 151652, "vision_end_token_id": 151653,
}


def write_qwen_vl(out: Path = QWEN_VL_DIR) -> Path:
    """Write the tiny Qwen2.5-VL processor folder (tokenizer, chat template, image/video processors)."""
    from transformers import Qwen2_5_VLProcessor
    from transformers.models.qwen2_vl import Qwen2VLImageProcessor
    from transformers.models.qwen2_vl.video_processing_qwen2_vl import Qwen2VLVideoProcessor

    tok = qwen_tokenizer()
    out.mkdir(parents=True, exist_ok=True)
    Qwen2_5_VLProcessor(image_processor=Qwen2VLImageProcessor(min_pixels=4 * 28 * 28, max_pixels=TINY_PIXELS),
                        tokenizer=tok, video_processor=Qwen2VLVideoProcessor(),
                        chat_template=CHAT_TEMPLATE).save_pretrained(out)
    return out


def _qwen_ids() -> dict:
    from transformers import AutoTokenizer

    return {**TINY_QWEN, **qwen_vision_ids(AutoTokenizer.from_pretrained(QWEN_VL_DIR))}


def _config(spec: TinySpec, vlm_config: dict, vlm_base: str, image_size: int, pixels: tuple[int, int] | None,
            device: str):
    from lerobot.policies.eo1.configuration_eo1 import EO1Config

    kwargs = {} if pixels is None else {"image_min_pixels": pixels[0], "image_max_pixels": pixels[1]}
    return EO1Config(vlm_base=vlm_base, vlm_config=vlm_config, device=device,
                     input_features=_visual_features(spec, image_size), output_features=_action_features(spec),
                     **kwargs)


def eo1_tiny_config(spec: TinySpec, device: str, image_size: int = TINY_IMAGE_SIZE):
    """Tiny EO-1 at the dataset's `image_size` (the processor resizes to the tiny pixel bound)."""
    config = _config(spec, _qwen_ids(), str(QWEN_VL_DIR), image_size, (4 * 28 * 28, TINY_PIXELS), device)
    config.chunk_size = config.n_action_steps = spec.chunk_size
    config.num_denoise_steps = spec.num_steps
    config.max_state_dim, config.max_action_dim = max(spec.state_dim, 8), max(spec.action_dim, 8)
    config.dtype = "float32"
    config.attn_implementation = "sdpa"
    return config


def eo1_released_config(cameras: tuple[str, ...], image_size: int, state_dim: int, action_dim: int, device: str):
    """lerobot/eo1-base's geometry for a dataset (IPEC-COMMUNITY/EO-1-3B converted: Qwen/Qwen2.5-VL-3B-Instruct,
    chunk 16, state/action padded to 32, two action-projector layers, 10 denoising steps; lerobot's defaults
    otherwise)."""
    spec = TinySpec(cameras=cameras, state_dim=state_dim, action_dim=action_dim)
    config = _config(spec, QWEN25_VL_3B, "Qwen/Qwen2.5-VL-3B-Instruct", image_size, None, device)
    config.chunk_size = 16
    return config


def construct(config):
    """EO1Policy(config) from the config alone: lerobot builds the VLM with `_from_config` when the config has a
    `pretrained_path` (a checkpoint's weights follow), else downloads `vlm_base`'s weights."""
    from lerobot.policies.eo1.modeling_eo1 import EO1Policy

    saved, config.pretrained_path = config.pretrained_path, config.pretrained_path or Path("graftcache-no-weights")
    try:
        return EO1Policy(config)
    finally:
        config.pretrained_path = saved


def build_tiny_eo1(spec: TinySpec, stats: dict | None, device: str):
    """Random-init tiny EO-1 + its lerobot pre/post processors (deterministic for `spec.seed`)."""
    from lerobot.policies.eo1.processor_eo1 import make_eo1_pre_post_processors

    config = eo1_tiny_config(spec, device)
    policy = seeded_policy(spec.seed, lambda: construct(config))
    pre, post = make_eo1_pre_post_processors(config, dataset_stats=_require_stats(stats))
    return policy.to(device), pre, post


if __name__ == "__main__":
    folder = write_qwen_vl()
    print(folder, sorted(p.name for p in folder.iterdir()))
