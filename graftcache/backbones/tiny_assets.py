"""Generate the small tokenizer/config folders shipped under graftcache/resources/tiny/ (run once).

Why shipped files instead of building them at import time: byte-level BPE training is fast, but its
merges may change between `tokenizers` releases, and a tiny backbone trained by train-tiny saved today
must still see the same token ids next year. So the files are generated once by this script,
committed (~100 KB), and loaded offline by `graftcache.backbones.tiny`.

    python -m graftcache.backbones.tiny_assets          # rewrites graftcache/resources/tiny/

Two folders:
- `smolvlm/`: usable as `SmolVLAConfig.vlm_model_name`. SmolVLA reads `AutoConfig`, `AutoProcessor`
  (only `tokenizer.fake_image_token_id` / `global_image_token_id`) and `AutoTokenizer` from it.
  The config fixes the tiny SmolVLM geometry (SigLIP 128 px / patch 16 -> 8x8 patches, pixel
  shuffle 2 -> 4x4 = 16 tokens per camera, Llama text model 192 wide x 4 layers).
- `paligemma/`: a PaliGemma-style tokenizer (<pad>=0, <eos>=1, <bos>=2, prepends <bos>) that
  replaces the gated `google/paligemma-3b-pt-224` tokenizer lerobot's pi0.5 processor hard-codes.

It also holds the Qwen-VL pieces the other tiny folders share: the tokenizer, Qwen3-VL's chat template, and
`write_qwen3_vl`, which writes `qwen3_vl/` (`python -m graftcache.backbones.vla_jepa.tiny`) and, with one text layer
more, `groot/` (`python -m graftcache.backbones.groot.tiny`).
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

TINY_ROOT = Path(__file__).resolve().parent.parent / "resources" / "tiny"
SMOLVLM_DIR = TINY_ROOT / "smolvlm"
PALIGEMMA_DIR = TINY_ROOT / "paligemma"
QWEN3_VL_DIR = TINY_ROOT / "qwen3_vl"

VOCAB_SIZE = 1024
SMOLVLM_SPECIALS = (
    "<|endoftext|>", "<|im_start|>", "<|im_end|>",
    "<fake_token_around_image>", "<image>", "<global-img>", "<end_of_utterance>",
)
PALIGEMMA_SPECIALS = ("<pad>", "<eos>", "<bos>", "<unk>", "<image>")
#: Qwen-VL's special tokens, what the tiny Qwen2.5-VL and Qwen3-VL folders (EO-1, Wall-X, GR00T, VLA-JEPA) hold.
QWEN_SPECIALS = ("<|endoftext|>", "<|im_start|>", "<|im_end|>", "<|vision_start|>", "<|vision_end|>",
                 "<|image_pad|>", "<|video_pad|>")
#: Qwen3-VL's chat template, reduced to what a VLA prompt uses (one user message, images as
#: vision_start/image_pad/vision_end, then text; no default system message, unlike Qwen2-VL's; the assistant turn
#: opened by add_generation_prompt).
QWEN3_VL_CHAT_TEMPLATE = (
    "{% for message in messages %}<|im_start|>{{ message['role'] }}\n"
    "{% if message['content'] is string %}{{ message['content'] }}{% else %}"
    "{% for content in message['content'] %}"
    "{% if content['type'] == 'image' or 'image' in content %}<|vision_start|><|image_pad|><|vision_end|>"
    "{% elif content['type'] == 'video' or 'video' in content %}<|vision_start|><|video_pad|><|vision_end|>"
    "{% elif 'text' in content %}{{ content['text'] }}{% endif %}{% endfor %}{% endif %}<|im_end|>\n"
    "{% endfor %}{% if add_generation_prompt %}<|im_start|>assistant\n{% endif %}"
)

#: Qwen3-VL's patch and merge sizes: one merged token per 32x32 pixels.
QWEN3_VL_PATCH, QWEN3_VL_MERGE = 16, 2
#: Qwen/Qwen3-VL-2B-Instruct's image-processor pixel bounds (size.shortest_edge / longest_edge of its
#: preprocessor_config.json), which GR00T's Cosmos-Reason2-2B keeps.
QWEN3_VL_PIXELS = (65536, 16777216)
#: The tiny Qwen3-VL processor's pixel bounds: 4 to 16 merged tokens an image.
TINY_QWEN3_VL_PIXELS = (4 * (QWEN3_VL_PATCH * QWEN3_VL_MERGE) ** 2, 16 * (QWEN3_VL_PATCH * QWEN3_VL_MERGE) ** 2)
#: The tiny Qwen3-VL config (VLA-JEPA's VLM, and GR00T's backbone with one text layer more: tiny_groot.py).
TINY_QWEN3_VL = {
    "vision_config": {"depth": 2, "hidden_size": 32, "intermediate_size": 64, "num_heads": 2, "in_channels": 3,
                      "out_hidden_size": 64, "patch_size": QWEN3_VL_PATCH, "spatial_merge_size": QWEN3_VL_MERGE,
                      "temporal_patch_size": 2, "num_position_embeddings": 64, "deepstack_visual_indexes": [0]},
    "text_config": {"hidden_size": 64, "intermediate_size": 128, "num_hidden_layers": 2, "num_attention_heads": 4,
                    "num_key_value_heads": 2, "head_dim": 16, "vocab_size": 1088, "max_position_embeddings": 1024,
                    "rope_parameters": {"rope_type": "default", "mrope_section": [4, 2, 2], "mrope_interleaved": True,
                                        "rope_theta": 10000.0},
                    "tie_word_embeddings": True},
    "tie_word_embeddings": True,
}

# SmolVLM geometry baked into smolvlm/config.json.
SMOLVLM_GEOMETRY = {
    "image_size": 128, "patch_size": 16, "scale_factor": 2,
    "vision_hidden": 96, "vision_layers": 2, "vision_heads": 3, "vision_intermediate": 384,
    "text_hidden": 192, "text_layers": 4, "text_heads": 6, "text_kv_heads": 2, "text_intermediate": 512,
}


def _corpus() -> list[str]:
    """LIBERO instructions plus the pi0.5 prompt scaffolding and state bins, so both tokenise compactly."""
    tasks_file = TINY_ROOT.parent / "libero_suite_tasks.json"
    tasks = [t for suite in json.loads(tasks_file.read_text()).values() for t in suite]
    numbers = " ".join(str(i) for i in range(256))
    scaffold = [f"Task: {t}, State: {numbers};\nAction: " for t in tasks[:8]]
    return (tasks + [t + "\n" for t in tasks] + scaffold) * 4


def train_bpe(specials: tuple[str, ...]):
    from tokenizers import Tokenizer, decoders, models, pre_tokenizers, trainers

    tok = Tokenizer(models.BPE(unk_token=None))
    tok.pre_tokenizer = pre_tokenizers.ByteLevel(add_prefix_space=False)
    tok.decoder = decoders.ByteLevel()
    trainer = trainers.BpeTrainer(
        vocab_size=VOCAB_SIZE, special_tokens=list(specials),
        initial_alphabet=pre_tokenizers.ByteLevel.alphabet(), show_progress=False,
    )
    tok.train_from_iterator(_corpus(), trainer=trainer)
    return tok


def qwen_tokenizer():
    """The tiny Qwen-VL tokenizer: byte-level BPE over the shared corpus with Qwen's specials."""
    from transformers import PreTrainedTokenizerFast

    return PreTrainedTokenizerFast(tokenizer_object=train_bpe(QWEN_SPECIALS), eos_token="<|im_end|>",
                                   pad_token="<|endoftext|>", unk_token="<|endoftext|>")


def qwen_vision_ids(tok) -> dict[str, int]:
    """The vision token ids a Qwen-VL config names, read from its tokenizer."""
    return {name: tok.convert_tokens_to_ids(t) for name, t in (
        ("image_token_id", "<|image_pad|>"), ("video_token_id", "<|video_pad|>"),
        ("vision_start_token_id", "<|vision_start|>"), ("vision_end_token_id", "<|vision_end|>"))}


def write_qwen3_vl(out: Path = QWEN3_VL_DIR, text: Mapping[str, Any] | None = None) -> Path:
    """Write a tiny Qwen3-VL folder: the tiny config (`text` overrides fields of its text config), the tiny Qwen
    tokenizer with Qwen3-VL's chat template, Qwen2-VL's image processor at Qwen3-VL's settings (patch 16, merge 2,
    temporal patch 2, mean/std 0.5) within TINY_QWEN3_VL_PIXELS, and Qwen3-VL's video processor."""
    from transformers import Qwen3VLConfig, Qwen3VLProcessor
    from transformers.models.qwen2_vl import Qwen2VLImageProcessor
    from transformers.models.qwen3_vl.video_processing_qwen3_vl import Qwen3VLVideoProcessor

    tok = qwen_tokenizer()
    pixels = {"shortest_edge": TINY_QWEN3_VL_PIXELS[0], "longest_edge": TINY_QWEN3_VL_PIXELS[1]}
    images = Qwen2VLImageProcessor(size=pixels, patch_size=QWEN3_VL_PATCH, merge_size=QWEN3_VL_MERGE,
                                   temporal_patch_size=2, image_mean=[0.5] * 3, image_std=[0.5] * 3)
    out.mkdir(parents=True, exist_ok=True)
    Qwen3VLProcessor(image_processor=images, tokenizer=tok, video_processor=Qwen3VLVideoProcessor(),
                     chat_template=QWEN3_VL_CHAT_TEMPLATE).save_pretrained(out)
    config = {**TINY_QWEN3_VL, "text_config": {**TINY_QWEN3_VL["text_config"], **(text or {})}}
    Qwen3VLConfig(**config, **qwen_vision_ids(tok)).save_pretrained(out)
    return out

def write_smolvlm(out: Path = SMOLVLM_DIR) -> Path:
    from transformers import PreTrainedTokenizerFast, SmolVLMConfig
    from transformers.models.smolvlm import SmolVLMImageProcessor, SmolVLMProcessor
    from transformers.models.smolvlm.video_processing_smolvlm import SmolVLMVideoProcessor

    g = SMOLVLM_GEOMETRY
    tok = PreTrainedTokenizerFast(
        tokenizer_object=train_bpe(SMOLVLM_SPECIALS),
        bos_token="<|im_start|>", eos_token="<end_of_utterance>", pad_token="<|im_end|>",
        unk_token="<|endoftext|>",
        extra_special_tokens={
            "fake_image_token": "<fake_token_around_image>", "image_token": "<image>",
            "global_image_token": "<global-img>", "end_of_utterance_token": "<end_of_utterance>",
        },
    )
    cfg = SmolVLMConfig(
        image_token_id=tok.convert_tokens_to_ids("<image>"),
        scale_factor=g["scale_factor"],
        pad_token_id=tok.pad_token_id,
        vision_config={
            "hidden_size": g["vision_hidden"], "intermediate_size": g["vision_intermediate"],
            "num_hidden_layers": g["vision_layers"], "num_attention_heads": g["vision_heads"],
            "image_size": g["image_size"], "patch_size": g["patch_size"],
        },
        text_config={
            "model_type": "llama", "hidden_size": g["text_hidden"], "intermediate_size": g["text_intermediate"],
            "num_hidden_layers": g["text_layers"], "num_attention_heads": g["text_heads"],
            "num_key_value_heads": g["text_kv_heads"], "head_dim": g["text_hidden"] // g["text_heads"],
            "vocab_size": len(tok), "max_position_embeddings": 2048, "rope_theta": 100000.0,
            "rms_norm_eps": 1e-5, "pad_token_id": tok.pad_token_id,
        },
    )
    out.mkdir(parents=True, exist_ok=True)
    cfg.save_pretrained(out)
    tokens_per_image = (g["image_size"] // g["patch_size"]) ** 2 // g["scale_factor"] ** 2
    SmolVLMProcessor(
        image_processor=SmolVLMImageProcessor(
            size={"longest_edge": g["image_size"]}, max_image_size={"longest_edge": g["image_size"]}
        ),
        tokenizer=tok,
        video_processor=SmolVLMVideoProcessor(),
        image_seq_len=tokens_per_image,
    ).save_pretrained(out)
    return out


def write_paligemma(out: Path = PALIGEMMA_DIR) -> Path:
    from tokenizers import processors
    from transformers import PreTrainedTokenizerFast

    bpe = train_bpe(PALIGEMMA_SPECIALS)
    bpe.post_processor = processors.TemplateProcessing(
        single="<bos> $A", pair="<bos> $A $B", special_tokens=[("<bos>", bpe.token_to_id("<bos>"))]
    )
    tok = PreTrainedTokenizerFast(
        tokenizer_object=bpe, bos_token="<bos>", eos_token="<eos>", pad_token="<pad>", unk_token="<unk>"
    )
    out.mkdir(parents=True, exist_ok=True)
    tok.save_pretrained(out)
    return out



# ------------------------------------------------------------------------------------ Qwen2.5-VL (EO-1, Wall-X)
QWEN_VL_DIR = TINY_ROOT / "qwen2_5_vl"
QWEN_VL_TINY_PIXELS = 16 * 28 * 28  # max pixels of the tiny processor: 112 x 112
#: Qwen2-VL's chat template (what Qwen/Qwen2.5-VL-3B-Instruct ships): images as vision_start/image_pad/vision_end.
QWEN25_VL_CHAT_TEMPLATE = (
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
TINY_QWEN25_VL = {
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
    Qwen2_5_VLProcessor(image_processor=Qwen2VLImageProcessor(min_pixels=4 * 28 * 28, max_pixels=QWEN_VL_TINY_PIXELS),
                        tokenizer=tok, video_processor=Qwen2VLVideoProcessor(),
                        chat_template=QWEN25_VL_CHAT_TEMPLATE).save_pretrained(out)
    return out


def qwen25_vl_ids() -> dict:
    """The tiny Qwen2.5-VL config with the tiny tokenizer's vision token ids."""
    from transformers import AutoTokenizer

    return {**TINY_QWEN25_VL, **qwen_vision_ids(AutoTokenizer.from_pretrained(QWEN_VL_DIR))}


if __name__ == "__main__":
    for d in (write_smolvlm(), write_paligemma()):
        print(d, sorted(p.name for p in d.iterdir()), sum(p.stat().st_size for p in d.iterdir()), "bytes")
