"""Tiny SmolVLA and pi0.5 policies built offline from the assets in graftcache/resources/tiny/.

They are lerobot's own policy classes at small sizes, so every code path (processors, graft,
loss, sampling, save/load) is the real one; only the widths and depths shrink. Geometries are
chosen so image tokens can matter: several tokens per camera, two cameras, and (pi0.5) adaRMS
gates that start open.

- SmolVLA: SigLIP 96 wide x 2 layers at 128 px / patch 16 -> 8x8 patches, pixel shuffle 2 -> 4x4 =
  16 tokens per camera, Llama text model 192 wide x 4 layers, expert 144 wide (lerobot's 0.75).
- pi0.5: SigLIP 96 wide x 2 layers at 56 px / patch 14 -> 4x4 = 16 tokens per camera, Gemma 128
  wide x 3 layers, expert 64 wide x 3 layers (8 heads x 1 KV head, as lerobot hard-codes),
  vocabulary shrunk from 257152 to 1024 (the tiny tokenizer has 771 tokens).
- pi0 (graftcache.backbones.pi0) and pi0-FAST (graftcache.backbones.pi0_fast) take pi0.5's geometry;
  pi0-FAST's vocabulary is the tiny tokenizer's 771, so every token it generates decodes.

pi0.5 hard-codes its sizes (`get_gemma_config` knows two variants; PaliGemma's projector width and
the 257152-token vocabulary are fixed in `PaliGemmaWithExpertModel.__init__`, lerobot 0.6
modeling_pi05.py:158-242), so `pi05_tiny_sizes` rebinds three module-level names of lerobot's
modeling_pi05 (the variant table and its PiGemma model classes) while a tiny policy is constructed or
loaded (pi0's and pi0-FAST's modules build PaliGemma the same way). A tiny checkpoint folder carries
`graftcache_tiny.json` so loading knows to do the same.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import io
import json
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import nn

from graftcache.backbones.tiny_assets import PALIGEMMA_DIR, SMOLVLM_DIR, SMOLVLM_GEOMETRY
from graftcache.errors import BackboneError

TINY_MARKER = "graftcache_tiny.json"


@dataclass(frozen=True)
class TinySpec:
    """What a tiny backbone must accept: the dataset's cameras and dims, plus chunking and the init seed."""

    cameras: tuple[str, ...] = ("image", "image2")   # LIBERO: observation.images.image / image2
    state_dim: int = 8
    action_dim: int = 7
    chunk_size: int = 10
    num_steps: int = 4                                 # flow-matching denoising steps at inference
    seed: int = 0


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


def _visual_features(spec: TinySpec, image_size: int) -> dict:
    from lerobot.configs.types import FeatureType, PolicyFeature

    return {
        **{f"observation.images.{c}": PolicyFeature(FeatureType.VISUAL, (3, image_size, image_size))
           for c in spec.cameras},
        "observation.state": PolicyFeature(FeatureType.STATE, (spec.state_dim,)),
    }


def _action_features(spec: TinySpec) -> dict:
    from lerobot.configs.types import FeatureType, PolicyFeature

    return {"action": PolicyFeature(FeatureType.ACTION, (spec.action_dim,))}


def _require_stats(stats: dict | None) -> dict:
    if stats is None:
        raise BackboneError("policy 'tiny' has no stored normalisation: pass dataset_stats (state and action)")
    return stats


# ---------------------------------------------------------------------------------------------- SmolVLA
def seeded_policy(seed: int, construct: Callable[[], nn.Module]) -> nn.Module:
    """`construct()` with the global RNG seeded to `seed` (and restored after) and its prints muted: a tiny
    policy's weights depend on its spec's seed only."""
    with torch.random.fork_rng(devices=[]), contextlib.redirect_stdout(io.StringIO()):
        torch.manual_seed(seed)
        return construct()


def smolvla_tiny_config(spec: TinySpec, device: str):
    from lerobot.policies.smolvla.configuration_smolvla import SmolVLAConfig

    size = SMOLVLM_GEOMETRY["image_size"]
    return SmolVLAConfig(
        vlm_model_name=str(SMOLVLM_DIR), load_vlm_weights=False,
        num_vlm_layers=SMOLVLM_GEOMETRY["text_layers"],
        resize_imgs_with_padding=(size, size),
        chunk_size=spec.chunk_size, n_action_steps=spec.chunk_size, num_steps=spec.num_steps,
        max_state_dim=max(spec.state_dim, 8), max_action_dim=max(spec.action_dim, 8),
        device=device,
        input_features=_visual_features(spec, size), output_features=_action_features(spec),
    )


def build_tiny_smolvla(spec: TinySpec, stats: dict | None, device: str):
    """Random-init tiny SmolVLA + its lerobot pre/post processors (deterministic for `spec.seed`)."""
    from lerobot.policies.smolvla.modeling_smolvla import SmolVLAPolicy
    from lerobot.policies.smolvla.processor_smolvla import make_smolvla_pre_post_processors

    config = smolvla_tiny_config(spec, device)
    policy = seeded_policy(spec.seed, lambda: SmolVLAPolicy(config))
    pre, post = make_smolvla_pre_post_processors(config, dataset_stats=_require_stats(stats))
    return policy.to(device), pre, post


# ---------------------------------------------------------------------------------------------- pi0.5
def paligemma_tiny_tokenizer():
    from transformers import AutoTokenizer

    return AutoTokenizer.from_pretrained(PALIGEMMA_DIR)


@contextlib.contextmanager
def pi05_tiny_sizes(geometry: Pi05TinyGeometry,
                    modeling: str = "lerobot.policies.pi05.modeling_pi05") -> Iterator[None]:
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
    names = tuple(n for n in ("get_gemma_config", "PaliGemmaForConditionalGenerationWithPiGemma", "PiGemmaForCausalLM")
                  if hasattr(m05, n))
    saved = tuple(getattr(m05, n) for n in names)
    real_paligemma, real_gemma = saved[1], saved[2] if len(saved) > 2 else None

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

    for name, value in zip(names, (variants.__getitem__, paligemma, gemma)):
        setattr(m05, name, value)
    try:
        yield
    finally:
        for name, value in zip(names, saved):
            setattr(m05, name, value)


def pi05_tiny_config(spec: TinySpec, geometry: Pi05TinyGeometry, device: str):
    from lerobot.policies.pi05.configuration_pi05 import PI05Config

    return PI05Config(
        chunk_size=spec.chunk_size, n_action_steps=spec.chunk_size, num_inference_steps=spec.num_steps,
        image_resolution=(geometry.image_size, geometry.image_size),
        max_state_dim=max(spec.state_dim, 8), max_action_dim=max(spec.action_dim, 8),
        tokenizer_max_length=geometry.tokenizer_max_length, device=device, dtype="float32",
        input_features=_visual_features(spec, geometry.image_size), output_features=_action_features(spec),
    )


def _open_adarms_gates(policy) -> None:
    """Random-init adaRMS starts with (near-)closed gates, so the expert ignores the prefix and a tiny
    pi0.5 barely sees its images. Open them: small random modulation, gate bias 1."""
    for module in policy.modules():
        dense = getattr(module, "dense", None)
        if type(module).__name__ == "PiGemmaRMSNorm" and dense is not None:
            torch.nn.init.normal_(dense.weight, std=0.02)
            torch.nn.init.zeros_(dense.bias)
            dense.bias.data[2 * module.dim:].fill_(1.0)


def pi05_processors(config, stats: dict | None, tokenizer, processor: str = "lerobot.policies.pi05.processor_pi05",
                    factory: str = "make_pi05_pre_post_processors"):
    """lerobot's pi0.5 (or pi0: `processor`, `factory`) processors with a given tokenizer (both processor
    modules hard-code the PaliGemma hub id: processor_pi05.py:145, processor_pi0.py:141)."""
    import importlib

    from lerobot.processor import TokenizerProcessorStep

    module = importlib.import_module(processor)
    saved = module.TokenizerProcessorStep
    module.TokenizerProcessorStep = functools.partial(TokenizerProcessorStep, tokenizer=tokenizer)
    try:
        return getattr(module, factory)(config, dataset_stats=stats)
    finally:
        module.TokenizerProcessorStep = saved


def build_tiny_pi05(spec: TinySpec, stats: dict | None, device: str, geometry: Pi05TinyGeometry | None = None):
    """Random-init tiny pi0.5 + its lerobot pre/post processors (deterministic for `spec.seed`)."""
    from lerobot.policies.pi05.modeling_pi05 import PI05Policy

    geometry = geometry or Pi05TinyGeometry()
    config = pi05_tiny_config(spec, geometry, device)
    with torch.random.fork_rng(devices=[]), pi05_tiny_sizes(geometry):
        torch.manual_seed(spec.seed)
        policy = PI05Policy(config)
        _open_adarms_gates(policy)
    pre, post = pi05_processors(config, _require_stats(stats), paligemma_tiny_tokenizer())
    return policy.to(device), pre, post


# ---------------------------------------------------------------------------------------------- marker
def write_marker(folder: Path, backbone: str, geometry: Pi05TinyGeometry | None) -> None:
    payload = {"backbone": backbone, "geometry": dataclasses.asdict(geometry) if geometry else None}
    (folder / TINY_MARKER).write_text(json.dumps(payload, indent=1))


def read_marker(folder: Path) -> dict | None:
    """The tiny marker of a checkpoint folder, or None for a regular checkpoint."""
    path = folder / TINY_MARKER
    if not path.exists():
        return None
    try:
        payload = json.loads(path.read_text())
        geometry = payload.get("geometry")
        return {"backbone": payload["backbone"], "geometry": Pi05TinyGeometry(**geometry) if geometry else None}
    except (ValueError, KeyError, TypeError) as exc:
        raise BackboneError(f"{path}: unreadable tiny-backbone marker ({exc})") from None
