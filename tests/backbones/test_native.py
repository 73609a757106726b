"""Native towers (smolvla-native, pi05-native, pi0-native, pi0_fast-native) as encoders: measured spec, outputs
equal to the policy's own tower and connector, the cache layout they produce, and their errors."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers.backbones import tiny
from helpers.datasets import Written

from graftcache.backbone_table import native_name
from graftcache.backbones.native import policy_pixels
from graftcache.encoders import get_spec, load_encoder
from graftcache.errors import EncoderError
from graftcache.extract import ExtractRequest, extract
from graftcache.store import FeatureCache

NAMES = ("smolvla", "pi05", "pi0", "pi0_fast")


@pytest.fixture(scope="module", params=NAMES)
def saved(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> tuple[str, Path]:
    """A tiny policy checkpoint folder as `--policy` names it."""
    folder = tmp_path_factory.mktemp(f"policy_{request.param}")
    tiny(request.param).save(folder)
    return request.param, folder


def test_registered_under_the_backbone_names() -> None:
    for name in NAMES:
        spec = get_spec(native_name(name))
        assert spec.library == "native" and spec.name == f"{name}-native"


def test_outputs_equal_the_policy_tower_and_connector(saved: tuple[str, Path]) -> None:
    name, folder = saved
    encoder = load_encoder(native_name(name), policy=str(folder))
    adapter = tiny(name)  # the same seed-0 weights, loaded independently
    assert encoder.weights_info["sha256"] == adapter.policy_sha256
    assert encoder.weights_info["random_init"] is True  # a tiny checkpoint is never released weights
    frames = torch.from_numpy(np.random.default_rng(0).integers(0, 256, (2, 64, 80, 3), dtype=np.uint8))
    x = encoder.preprocess(frames)
    assert x.shape == (2, 3, encoder.spec.image_size, encoder.spec.image_size) and 0 <= x.min() and x.max() <= 1
    pixels = policy_pixels(frames, encoder.spec.image_size).float() / 255
    torch.testing.assert_close(x, pixels, rtol=0, atol=0)
    grid, extras = encoder.forward_with_extras(x)
    torch.testing.assert_close(grid, adapter.native_patch_grid(pixels))
    torch.testing.assert_close(extras["connector"], adapter.native_tokens(pixels))
    assert (*encoder.spec.grid, encoder.spec.width) == tuple(grid.shape[1:])
    assert encoder.extra_shapes["connector"] == tuple(extras["connector"].shape[1:])


def test_extract_stores_grid_and_connector_tokens(saved: tuple[str, Path], v3_video: Written,
                                                  tmp_path: Path) -> None:
    name, folder = saved
    result = extract(ExtractRequest(dataset=str(v3_video.root), encoder=native_name(name), grids=("unpooled", "2x2"),
                                    policy=str(folder), num_workers=0, batch_size=4, cache=str(tmp_path),
                                    progress=False), log=lambda _: None)
    cache = FeatureCache(result.path)
    assert cache.complete
    manifest = cache.manifest
    assert manifest.encoder_name == native_name(name) and manifest.random_init is True
    connector = list(load_encoder(native_name(name), policy=str(folder)).extra_shapes["connector"])
    assert manifest.extras["connector"] == connector
    assert cache.n_frames == sum(len(f) for (_, key), f in v3_video.frames.items() if key == v3_video.cameras[0])
    shapes = cache.layout["arrays"]  # per-frame shapes
    width = manifest.encoder["width"]
    assert sorted(p for p in shapes if p.endswith("/2x2")) == [f"features/{c}/2x2" for c in ("image", "image2")]
    assert all(shapes[p] == [4, width] for p in shapes if p.endswith("/2x2"))
    gh, gw = manifest.encoder["grid"]  # `unpooled`: the tower's own pre-connector grid, measured on the policy
    assert manifest.grids == [f"{gh}x{gw}", "2x2"] and manifest.unpooled_grid == f"{gh}x{gw}"
    assert [shapes[f"features/{c}/{gh}x{gw}"] for c in ("image", "image2")] == [[gh * gw, width]] * 2
    assert [shapes[p] for p in shapes if p.endswith("/connector")] == [connector, connector]
    json.dumps(manifest.to_dict())  # the manifest stays plain JSON


def test_needs_a_policy_and_refuses_other_weights(saved: tuple[str, Path]) -> None:
    name, folder = saved
    with pytest.raises(EncoderError, match="needs --policy"):
        load_encoder(native_name(name))
    with pytest.raises(EncoderError, match="takes its weights from --policy"):
        load_encoder(native_name(name), policy=str(folder), random_init=True)
