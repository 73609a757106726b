"""The transformers vision architectures graftcache can turn into patch grids, keyed by config
`model_type`. Full two-tower checkpoints (SigLIP, CLIP) map to their vision model, which loads the
`vision_model.*` half of the weights and ignores the text tower.

Classes are named, not imported, so importing graftcache does not import every transformers model.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import transformers

from graftcache.errors import EncoderError

SIGLIP_TOKENS = ("transformers last_hidden_state: patch tokens after post_layernorm (the MAP head's pooled "
                 "output is not used); SigLIP has no prefix tokens")
CLIP_TOKENS = ("transformers last_hidden_state: tokens BEFORE the final post_layernorm (CLIP applies it only to "
               "the pooled CLS token); CLS dropped")
DINOV2_TOKENS = "transformers last_hidden_state: tokens after the final layernorm; CLS dropped"
DINOV2_REG_TOKENS = "transformers last_hidden_state: tokens after the final layernorm; CLS and register tokens dropped"
VIT_TOKENS = "transformers last_hidden_state: tokens after the final layernorm; CLS dropped"
RESNET_TOKENS = "transformers last_hidden_state: final stage feature map, before the pooler"


@dataclass(frozen=True)
class HFArch:
    """How one transformers vision model family yields tokens."""

    model_cls: str                         # transformers class name
    config_cls: str
    prefix: Callable[[object], int]        # config -> number of tokens before the patch tokens
    tokens: str                            # token definition for the manifest
    interpolate_kwarg: bool = False        # forward needs interpolate_pos_encoding at non-native sizes

    def model_class(self) -> type:
        return getattr(transformers, self.model_cls)

    def config_class(self) -> type:
        return getattr(transformers, self.config_cls)


_SIGLIP = HFArch("SiglipVisionModel", "SiglipVisionConfig", lambda c: 0, SIGLIP_TOKENS, interpolate_kwarg=True)
_CLIP = HFArch("CLIPVisionModel", "CLIPVisionConfig", lambda c: 1, CLIP_TOKENS, interpolate_kwarg=True)
_VIT = HFArch("ViTModel", "ViTConfig", lambda c: 1, VIT_TOKENS, interpolate_kwarg=True)

HF_ARCHS: dict[str, HFArch] = {
    "siglip": _SIGLIP,                     # fixed-resolution SigLIP and SigLIP2 checkpoints
    "siglip_vision_model": _SIGLIP,
    "clip": _CLIP,
    "clip_vision_model": _CLIP,
    "dinov2": HFArch("Dinov2Model", "Dinov2Config", lambda c: 1, DINOV2_TOKENS),
    "dinov2_with_registers": HFArch("Dinov2WithRegistersModel", "Dinov2WithRegistersConfig",
                                    lambda c: 1 + c.num_register_tokens, DINOV2_REG_TOKENS),
    "resnet": HFArch("ResNetModel", "ResNetConfig", lambda c: 0, RESNET_TOKENS),
    "vit": _VIT,
}


def arch_of(model_type: str, where: str) -> HFArch:
    try:
        return HF_ARCHS[model_type]
    except KeyError:
        raise EncoderError(f"{where}: transformers model_type {model_type!r} is not supported; supported: "
                           f"{', '.join(sorted(HF_ARCHS))} (NaFlex siglip2 is not: use a fixed-resolution "
                           f"SigLIP2 checkpoint such as google/siglip2-base-patch16-256)") from None
