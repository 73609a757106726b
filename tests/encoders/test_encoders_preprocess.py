"""Encoder.preprocess against independent implementations; describe(); input validation."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from helpers.encoders import random_frames
from PIL import Image
from torch import nn

from graftcache.encoders import Encoder, get_spec
from graftcache.errors import EncoderError

PIL_RESAMPLE = {"bicubic": Image.BICUBIC, "bilinear": Image.BILINEAR}


def _bare(name: str) -> Encoder:
    """An Encoder around no model: preprocess depends only on the spec."""
    return Encoder(get_spec(name), nn.Identity(), {})


@pytest.mark.parametrize(("name", "hw"), [("dinov2-s", (256, 256)), ("clip-b16", (256, 256)),
                                          ("mobilenetv2", (300, 300)), ("siglip2", (240, 320))])
def test_resize_matches_pil(name: str, hw: tuple[int, int]) -> None:
    """Antialiased tensor resize == PIL's resize (the reference recipe), per channel in PIL's float mode.

    PIL's 8-bit resize rounds to uint8 between its horizontal and vertical passes (up to ~2 px levels
    off for bicubic); its float mode ("F") runs the same filter without rounding, so the two must agree
    to a hundredth of a pixel level.
    """
    enc = _bare(name)
    spec = enc.spec
    frames = random_frames(3, *hw, seed=1)
    x = enc.preprocess(frames)
    assert x.shape == (3, 3, spec.image_size, spec.image_size) and x.dtype == torch.float32
    mean, std = np.array(spec.mean), np.array(spec.std)
    size = (spec.image_size, spec.image_size)
    for i in range(3):
        px = frames[i].numpy().astype(np.float32)
        resample = PIL_RESAMPLE[spec.interpolation]
        ref_px = np.stack([np.asarray(Image.fromarray(px[..., c], mode="F").resize(size, resample))
                           for c in range(3)], axis=-1).clip(0, 255)
        ours_px = (x[i].permute(1, 2, 0).double().numpy() * std + mean) * 255
        diff = np.abs(ours_px - ref_px)
        assert diff.max() < 0.01, (diff.max(), diff.mean())


def test_no_resize_when_frames_have_the_input_size() -> None:
    enc = _bare("siglip")  # 256 px input, mean = std = 0.5
    frames = random_frames(2, 256, 256, seed=2)
    expected = (frames.permute(0, 3, 1, 2).float() / 255 - 0.5) / 0.5
    assert torch.equal(enc.preprocess(frames), expected)


def test_imagenet_normalisation_per_channel() -> None:
    enc = _bare("resnet18")
    frames = torch.zeros(1, 256, 256, 3, dtype=torch.uint8)
    frames[..., 0], frames[..., 1], frames[..., 2] = 255, 128, 0
    x = enc.preprocess(frames)
    want = [(1.0 - 0.485) / 0.229, (128 / 255 - 0.456) / 0.224, (0.0 - 0.406) / 0.225]
    torch.testing.assert_close(x[0, :, 0, 0], torch.tensor(want))


@pytest.mark.parametrize("bad", [torch.zeros(2, 256, 256, 3), torch.zeros(2, 3, 256, 256, dtype=torch.uint8),
                                 torch.zeros(256, 256, 3, dtype=torch.uint8), np.zeros((1, 256, 256, 3), np.uint8)])
def test_preprocess_rejects_wrong_input(bad: object) -> None:
    with pytest.raises(EncoderError, match=r"uint8 tensor \[B,H,W,3\]"):
        _bare("resnet18").preprocess(bad)


def test_forward_grid_rejects_wrong_size() -> None:
    with pytest.raises(EncoderError, match=r"expects \[B,3,224,224\]"):
        _bare("dinov2-s").forward_grid(torch.zeros(1, 3, 256, 256))


def test_describe_is_the_recipe_and_json() -> None:
    d = _bare("clip-b16").describe()
    assert json.loads(json.dumps(d)) == d
    assert d == {
        "name": "clip-b16", "library": "transformers", "model_id": "openai/clip-vit-base-patch16", "image_size": 224,
        "preprocessing": {"resize": [224, 224], "crop": None, "interpolation": "bicubic", "antialias": True,
                          "rescale": 1 / 255, "mean": [0.48145466, 0.4578275, 0.40821073],
                          "std": [0.26862954, 0.26130258, 0.27577711]},
        "grid": [14, 14], "width": 768, "prefix_tokens": 1, "tokens": d["tokens"]}
    assert "BEFORE the final post_layernorm" in d["tokens"]
