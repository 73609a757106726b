"""Tiny and released EVO1 configurations (lerobot 0.6 `Evo1Config`: InternVL3 + a flow-matching action head),
buildable offline.

EVO1's `InternVL3Embedder` loads its tokenizer and its InternVL (transformers' native `InternVLModel`, no
trust_remote_code) with `AutoTokenizer.from_pretrained` / `AutoModel.from_pretrained(vlm_model_name)` in its
constructor, unconditionally: loading even a finetuned checkpoint (which holds the whole VLM's weights) first
fetches the base VLM's weights, and transformers refuses `from_pretrained` while parameters are built on the
meta device. `construct` therefore runs lerobot's constructor with that one call building the InternVL from
`vlm_model_name`'s config instead (`AutoModel.from_config`, in the dtype and attention lerobot asks for): the
same architecture, read from the same folder or hub snapshot (config.json and tokenizer only), no weights.

The tiny InternVL folder is shipped under graftcache/resources/tiny/internvl/ (generated once by
`python -m graftcache.backbones.evo1.tiny`, like tiny_assets.py's folders): config.json and a byte-level BPE
tokenizer carrying InternVL's image tokens `<img>`, `</img>`, `<IMG_CONTEXT>`.

- tiny: InternViT 32 wide x 2 layers at 112 px / patch 14 -> 8x8 patches (+ CLS, dropped) -> pixel shuffle 0.5
  -> 4x4 = 16 tokens per camera; projector LayerNorm(128) -> Linear(128, 64) -> GELU -> Linear(64, 64) into a
  Qwen2 text model 64 wide x 3 layers cut to 2 by `vlm_num_layers` (4 heads, 2 KV heads, vocabulary 1024 >= the
  tokenizer's); action head 64 wide x 2 blocks, chunk 10, 8 padded state/action dims.
- released (lerobot's defaults: OpenGVLab/InternVL3-1B-hf at 448 px, LM cut to 14 of its 24 layers, bf16):
  InternViT-300M 1024 wide x 24 layers, 448 / 14 -> 32x32 -> pixel shuffle -> 16x16 = 256 tokens per camera
  whatever the dataset's frame size (the embedder resizes every frame to 448), projector into the 896-wide
  Qwen2.5-0.5B LM; action head 896 wide x 8 blocks, chunk 50, 24 padded dims, 32 Euler steps.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from pathlib import Path

from graftcache.backbones.patching import patched
from graftcache.backbones.tiny import TinyBuild, action_features, build_seeded, print_written, visual_features
from graftcache.backbones.tiny_assets import TINY_ROOT, train_bpe

INTERNVL_DIR = TINY_ROOT / "internvl"
TINY_IMAGE_SIZE = 112  # the tiny InternViT's native size (EVO1 requires image_resolution == the tower's size)
INTERNVL_SPECIALS = ("<|endoftext|>", "<|im_start|>", "<|im_end|>", "<img>", "</img>", "<IMG_CONTEXT>")
TINY_INTERNVL = {
    "vision_config": {"hidden_size": 32, "num_hidden_layers": 2, "num_attention_heads": 2, "intermediate_size": 64,
                      "attention_bias": True, "image_size": [TINY_IMAGE_SIZE, TINY_IMAGE_SIZE], "patch_size": [14, 14]},
    "text_config": {"model_type": "qwen2", "hidden_size": 64, "intermediate_size": 128, "num_hidden_layers": 3,
                    "num_attention_heads": 4, "num_key_value_heads": 2, "vocab_size": 1024,
                    "max_position_embeddings": 2048, "rope_theta": 1000000.0},
    "downsample_ratio": 0.5, "image_seq_length": 16, "projector_hidden_act": "gelu",
}
#: OpenGVLab/InternVL3-1B-hf's config.json (the fields that set the geometry; the rest are transformers' defaults):
#: InternViT-300M-448px-V2.5 and Qwen2.5-0.5B's text model with InternVL's 151674-token vocabulary.
INTERNVL3_1B = {
    "vision_config": {"hidden_size": 1024, "num_hidden_layers": 24, "num_attention_heads": 16,
                      "intermediate_size": 4096, "attention_bias": True, "image_size": [448, 448],
                      "patch_size": [14, 14], "layer_scale_init_value": 0.1, "use_mean_pooling": True},
    "text_config": {"model_type": "qwen2", "hidden_size": 896, "intermediate_size": 4864, "num_hidden_layers": 24,
                    "num_attention_heads": 14, "num_key_value_heads": 2, "vocab_size": 151674,
                    "max_position_embeddings": 32768, "rope_theta": 1000000.0},
    "downsample_ratio": 0.5, "image_seq_length": 256, "projector_hidden_act": "gelu", "image_token_id": 151667,
}


def write_internvl(out: Path = INTERNVL_DIR, geometry: dict = TINY_INTERNVL) -> Path:
    """Write an InternVL folder as lerobot's embedder reads one: config.json (`geometry`, its image token the
    tokenizer's `<IMG_CONTEXT>`) and the tiny tokenizer (right padding, as EVO1's prompts assume)."""
    from transformers import InternVLConfig, PreTrainedTokenizerFast

    tok = PreTrainedTokenizerFast(tokenizer_object=train_bpe(INTERNVL_SPECIALS), eos_token="<|im_end|>",
                                  pad_token="<|endoftext|>", unk_token="<|endoftext|>", padding_side="right")
    out.mkdir(parents=True, exist_ok=True)
    tok.save_pretrained(out)
    InternVLConfig(**{**geometry, "image_token_id": tok.convert_tokens_to_ids("<IMG_CONTEXT>")}).save_pretrained(out)
    return out


@contextlib.contextmanager
def internvl_from_config() -> Iterator[None]:
    """While active, lerobot's EVO1 embedder builds its InternVL from `vlm_model_name`'s config (no weights):
    its module-level `AutoModel` is swapped for one whose `from_pretrained` is transformers' `from_config`."""
    from lerobot.policies.evo1 import internvl3_embedder
    from transformers import AutoConfig, AutoModel

    class FromConfig:
        @staticmethod
        def from_pretrained(name, torch_dtype=None, attn_implementation=None, low_cpu_mem_usage=None, **hub):
            config = AutoConfig.from_pretrained(name, **hub)
            return AutoModel.from_config(config, dtype=torch_dtype, attn_implementation=attn_implementation)

    with patched(internvl3_embedder, AutoModel=FromConfig):
        yield


def construct(config):
    """Evo1Policy(config) with its InternVL built from the config alone (a checkpoint's weights follow)."""
    from lerobot.policies.evo1.modeling_evo1 import Evo1Policy

    with internvl_from_config():
        return Evo1Policy(config)


def _config(tiny: TinyBuild, vlm: str, image_size: int, device: str, **fields):
    from lerobot.policies.evo1.configuration_evo1 import Evo1Config

    return Evo1Config(vlm_model_name=vlm, device=device, input_features=visual_features(tiny, image_size),
                      output_features=action_features(tiny), **fields)


def evo1_tiny_config(tiny: TinyBuild, device: str, image_size: int = 128):
    """Tiny EVO1 for frames of `image_size` (the embedder resizes them to the tower's 112 px). Stage 2 (the
    whole VLM finetuned, as train-tiny trains it): stage 1 would embed without gradients."""
    return _config(tiny, str(INTERNVL_DIR), image_size, device, training_stage="stage2",
                   image_resolution=(TINY_IMAGE_SIZE, TINY_IMAGE_SIZE), vlm_num_layers=2, vlm_dtype="float32",
                   use_flash_attn=False, enable_gradient_checkpointing=False, embed_dim=64, hidden_dim=64,
                   state_hidden_dim=64, num_heads=4, num_layers=2, chunk_size=tiny.chunk_size,
                   n_action_steps=tiny.chunk_size, num_inference_timesteps=tiny.num_steps,
                   max_state_dim=max(tiny.state_dim, 8), max_action_dim=max(tiny.action_dim, 8))


def evo1_released_config(cameras: tuple[str, ...], image_size: int, state_dim: int, action_dim: int, device: str,
                         vlm: str = "OpenGVLab/InternVL3-1B-hf"):
    """lerobot's EVO1 defaults for a dataset: InternVL3-1B-hf at 448 px, 14 LM layers, chunk 50, 24 padded dims."""
    return _config(TinyBuild(cameras=cameras, state_dim=state_dim, action_dim=action_dim), vlm, image_size, device)


def build_tiny(tiny: TinyBuild, stats: dict | None, device: str):
    """Random-init tiny EVO1 and its processors (graftcache.backbones.tiny.build_seeded)."""
    from lerobot.policies.evo1.processor_evo1 import make_evo1_pre_post_processors

    return build_seeded(tiny, stats, device, evo1_tiny_config(tiny, device), construct, make_evo1_pre_post_processors)


if __name__ == "__main__":
    print_written(write_internvl())
