"""The PaliGemma family (pi0.5, pi0, pi0-FAST): its tiny sizes, tiny tokenizer, processors with a given tokenizer, and
its attention paths.

pi0.5 hard-codes its sizes (`get_gemma_config` knows two variants; PaliGemma's projector width and
the 257152-token vocabulary are fixed in `PaliGemmaWithExpertModel.__init__`, lerobot 0.6
modeling_pi05.py:158-242), so `pi05_tiny_sizes` rebinds three module-level names of lerobot's
modeling_pi05 (the variant configs and its PiGemma model classes) while a tiny policy is constructed or
loaded (pi0's and pi0-FAST's modules build PaliGemma the same way).

- tiny geometry (`Pi05TinyGeometry`): SigLIP 96 wide x 2 layers at 56 px / patch 14 -> 4x4 = 16 tokens per camera,
  Gemma 128 wide x 3 layers, expert 64 wide x 3 layers (8 heads x 1 KV head, as lerobot hard-codes), vocabulary
  shrunk from 257152 to 1024 (the tiny tokenizer has 771 tokens). pi0 and pi0-FAST take pi0.5's geometry;
  pi0-FAST's vocabulary is the tiny tokenizer's 771, so every token it generates decodes.

Attention (graftcache/backbones/attention.py): pi0 and pi0.5 attend through transformers' module global
`modeling_gemma.eager_attention_forward` (their joint layer calls it, and lerobot sets every Gemma config to eager
before prefix and denoising calls); `gemma_fused` puts `GemmaAttentionForward` there, which runs the marked
GemmaAttention modules of one policy fused and every other caller's as before. pi0-FAST is left at the sdpa
attention transformers builds it with; `gemma_eager` pins its Gemma configs to eager. Gemma 1 has no soft-capping.
"""

from __future__ import annotations

import contextlib
import functools
from collections.abc import Iterator
from dataclasses import dataclass

import torch
from torch import nn

from graftcache.backbones.attention import EAGER, FUSED, fused_attention
from graftcache.backbones.patching import Patches, patched
from graftcache.backbones.tiny_assets import PALIGEMMA_DIR

PI05_MODELING = "lerobot.policies.pi05.modeling_pi05"


@dataclass(frozen=True)
class Pi05TinyGeometry:
    lm_width: int = 128
    lm_mlp: int = 256
    expert_width: int = 64
    expert_mlp: int = 128
    depth: int = 3                # LM and expert must share depth and head size (modeling_pi05.py:267)
    head_dim: int = 16
    vision_width: int = 96
    vision_mlp: int = 384
    vision_layers: int = 2
    vision_heads: int = 3
    patch_size: int = 14
    image_size: int = 56
    vocab_size: int = 1024        # >= the tiny PaliGemma tokenizer's size (771)
    tokenizer_max_length: int = 80


def paligemma_tiny_tokenizer():
    from transformers import AutoTokenizer

    return AutoTokenizer.from_pretrained(PALIGEMMA_DIR)


@contextlib.contextmanager
def pi05_tiny_sizes(geometry: Pi05TinyGeometry,
                    modeling: str = PI05_MODELING) -> Iterator[None]:
    """Construct lerobot PaliGemma policies at `geometry` instead of gemma_2b / gemma_300m / So400m.

    `modeling` is the lerobot module whose names are rebound: pi0.5's, pi0's or pi0-FAST's (all three build
    PaliGemma the same way; pi0-FAST has no expert and no PiGemmaForCausalLM, and leaves SigLIP at 224 px, so
    the vision config's image size is set here too)."""
    import importlib

    m05 = importlib.import_module(modeling)
    g = geometry
    variants = {
        "gemma_2b": m05.GemmaConfig(g.lm_width, g.depth, g.lm_mlp, 8, 1, g.head_dim),
        "gemma_300m": m05.GemmaConfig(g.expert_width, g.depth, g.expert_mlp, 8, 1, g.head_dim),
    }
    real_paligemma = m05.PaliGemmaForConditionalGenerationWithPiGemma
    real_gemma = getattr(m05, "PiGemmaForCausalLM", None)

    def paligemma(config):
        vision = config.vision_config
        vision.hidden_size, vision.intermediate_size = g.vision_width, g.vision_mlp
        vision.num_hidden_layers, vision.num_attention_heads = g.vision_layers, g.vision_heads
        vision.patch_size, vision.projection_dim, vision.image_size = g.patch_size, g.lm_width, g.image_size
        config._vocab_size = config.text_config.vocab_size = g.vocab_size
        config.image_token_index = g.vocab_size - 1
        return real_paligemma(config=config)

    def gemma(config):
        config.vocab_size = g.vocab_size
        return real_gemma(config=config)

    sizes = {"get_gemma_config": variants.__getitem__, "PaliGemmaForConditionalGenerationWithPiGemma": paligemma,
             "PiGemmaForCausalLM": gemma}
    sizes = {name: value for name, value in sizes.items() if hasattr(m05, name)}
    with patched(m05, **sizes):
        yield



def pi05_processors(config, stats: dict | None, tokenizer, processor: str = "lerobot.policies.pi05.processor_pi05",
                    factory: str = "make_pi05_pre_post_processors"):
    """lerobot's pi0.5 (or pi0: `processor`, `factory`) processors with a given tokenizer (both processor
    modules hard-code the PaliGemma hub id: processor_pi05.py:145, processor_pi0.py:141)."""
    import importlib

    from lerobot.processor import TokenizerProcessorStep

    module = importlib.import_module(processor)
    with patched(module, TokenizerProcessorStep=functools.partial(TokenizerProcessorStep, tokenizer=tokenizer)):
        return getattr(module, factory)(config, dataset_stats=stats)




#: Set on a policy's GemmaAttention modules while they attend fused (GemmaAttentionForward reads it).
FUSED_MARK = "_graftcache_fused_attention"


class GemmaAttentionForward:
    """`modeling_gemma.eager_attention_forward` while a PaliGemma policy attends fused: the fused kernel for attention
    modules carrying FUSED_MARK, the function it replaced (`eager`) for every other."""

    def __init__(self, eager) -> None:
        self.eager = eager

    def __call__(self, module: nn.Module, query: torch.Tensor, key: torch.Tensor, value: torch.Tensor,
                 attention_mask: torch.Tensor | None, scaling: float, dropout: float = 0.0, **kwargs):
        if not getattr(module, FUSED_MARK, False):
            return self.eager(module, query, key, value, attention_mask, scaling, dropout, **kwargs)
        out = fused_attention(query, key, value, attention_mask, scaling, dropout if module.training else 0.0)
        return out.transpose(1, 2).contiguous(), None  # eager's [B, L, heads, D]; no probabilities were made


def _gemma_attentions(policy: nn.Module) -> list[nn.Module]:
    from transformers.models.gemma.modeling_gemma import GemmaAttention

    return [m for m in policy.modules() if isinstance(m, GemmaAttention)]


def gemma_fused(patches: Patches, policy: nn.Module) -> None:
    """`policy`'s Gemma attention (LM and expert) through the fused kernel: GemmaAttentionForward at the module global
    (unless another policy's patches put it there already) and every GemmaAttention module marked."""
    from transformers.models.gemma import modeling_gemma

    if not isinstance(modeling_gemma.eager_attention_forward, GemmaAttentionForward):
        patches.set(modeling_gemma, "eager_attention_forward",
                    GemmaAttentionForward(modeling_gemma.eager_attention_forward))
    for module in _gemma_attentions(policy):
        patches.set(module, FUSED_MARK, True)


def gemma_eager(patches: Patches, policy: nn.Module) -> None:
    """`policy`'s Gemma configs set to eager (transformers' `_attn_implementation`, which GemmaAttention dispatches
    on), as lerobot's pi0 and pi0.5 set theirs before every call."""
    configs = {id(m.config): m.config for m in _gemma_attentions(policy)}
    for config in configs.values():
        patches.set(config, "_attn_implementation_internal", "eager")


#: How a PaliGemma policy is made to attend with another path than lerobot's own.
GEMMA_ATTENTIONS = {EAGER: gemma_eager, FUSED: gemma_fused}
