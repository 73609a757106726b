"""X-VLA as a backbone: tiny geometry, the native tower against the policy's own image path, the loss and
the sampler against lerobot's `forward` / `generate_actions` under the same random draws, padding, the graft
slots (view 0 into the Florence-2 encoder, view 1 into the action transformer), save/load, and the released
geometry on the meta device (0.9B parameters are never materialised here)."""

from __future__ import annotations

import json
import math

import pytest
import torch
from helpers.backbones import (
    ENC_DIM,
    activation_checkpointing_peaks,
    assert_native_control_reproduces,
    fixed_noise_time,
    grafted,
    raw_features,
    raw_images,
    tiny,
)

from devtools.released import hub_cache, publish
from graftcache.backbones import load_backbone
from graftcache.backbones.xvla.adapter import XVLAAdapter, conv_grid
from graftcache.graft import GraftProjector, feature_key


def test_tiny_geometry() -> None:
    adapter = tiny("xvla")
    assert adapter.token_grid == (4, 4) and adapter.lm_width == 64 and adapter.embed_scale == 1.0
    assert adapter.cameras == ("image", "image2") and adapter.max_action_dim == 8 and adapter.chunk_size == 10
    images = torch.rand(2, 3, 200, 160)  # any size: the tiny config resizes with padding to 128
    grid, tokens = adapter.native_patch_grid(images), adapter.native_tokens(images)
    assert grid.shape == (2, 4, 4, 64) and tokens.shape == (2, 1 + 16, 64)  # spatial-mean token + the grid
    assert sum(p.numel() for p in adapter.policy.parameters()) == 528_952


def test_native_tower_is_the_policys_own_image_path() -> None:
    """The native tokens equal what `forward_vlm` embeds for view 0 after lerobot's preprocessor."""
    adapter = tiny("xvla")
    raw = raw_images(adapter, 3)
    batch = adapter.prepare(raw)
    pixels, masks = adapter.policy._prepare_images(batch)
    assert pixels.shape[:2] == (3, 2) and masks.all()
    with torch.no_grad():
        own = adapter.policy.model.vlm.get_image_features(pixels[:, 0]).pooler_output
    torch.testing.assert_close(adapter.native_tokens(raw["observation.images.image"]), own)
    davit = adapter.policy.model.vlm.vision_tower(pixels[:, 1]).last_hidden_state
    torch.testing.assert_close(adapter.native_patch_grid(raw["observation.images.image2"]), davit.permute(0, 2, 3, 1))


def test_loss_and_prediction_are_lerobots_under_the_same_draws() -> None:
    adapter = tiny("xvla")
    adapter.policy.eval()
    raw = raw_images(adapter, 4)
    raw["action_is_pad"][:] = False  # lerobot's forward does not mask padding
    batch = adapter.prepare(raw)
    size, chunk, dim = 4, adapter.chunk_size, adapter.max_action_dim
    with torch.no_grad():
        torch.manual_seed(7)
        reference, _ = adapter.policy.forward(dict(batch))
        torch.manual_seed(7)  # modeling_xvla.py draws the noise levels, then the noise
        time = (torch.rand(1) + torch.arange(size) / size) % (1 - 1e-5)
        noise = torch.randn(size, chunk, dim)
        ours = adapter.loss(batch, noise, time)
        torch.testing.assert_close(ours.mean(), reference)
        torch.manual_seed(11)
        chunk_ref = adapter.policy.predict_action_chunk(dict(batch))
        torch.manual_seed(11)
        start = torch.randn(size, chunk, dim)
    torch.testing.assert_close(adapter.predict(batch, start), chunk_ref)
    assert chunk_ref.shape == (size, chunk, adapter.action_dim)


def test_loss_is_the_mse_over_real_steps_and_dims_per_sample() -> None:
    """The "auto" action space's loss is the MSE over the real action dims; padded steps (sample 0's last 3)
    are left out per sample. X-VLA's transformer is not causal over the chunk, so padded targets still enter
    the noisy input of every step, as they do in lerobot's own training."""
    adapter = tiny("xvla")
    adapter.policy.eval()  # X-VLA's transformer has dropout 0.1 (lerobot's, kept in training)
    batch = adapter.prepare(raw_images(adapter, 3))
    noise, time = fixed_noise_time(adapter, 3)
    preds = []
    hook = adapter.policy.model.transformer.register_forward_hook(lambda m, a, out: preds.append(out))
    with torch.no_grad():
        loss = adapter.loss(batch, noise, time)
    hook.remove()
    error = (preds[0][:, :, :7] - batch["action"]) ** 2
    torch.testing.assert_close(loss, torch.stack([error[0, :-3].mean(), error[1].mean(), error[2].mean()]))


def test_graft_feeds_view0_to_the_lm_and_view1_to_the_action_transformer() -> None:
    adapter = grafted("xvla")
    assert {n for n, p in adapter.policy.named_parameters() if p.requires_grad} == {
        f"model.vlm.multi_modal_projector.{p}" for p in ("norm.weight", "norm.bias", "proj.weight", "proj.bias")}
    raw = raw_features(adapter, 2)
    seen = {}
    transformer = adapter.policy.model.transformer
    hook = transformer.register_forward_hook(lambda m, args, kwargs, out: seen.update(kwargs), with_kwargs=True)
    images, masks = adapter.policy._prepare_images(adapter.prepare(raw))
    assert images.shape == (2, 2, 16, ENC_DIM) and masks.all()
    noise, time = fixed_noise_time(adapter, 2)
    loss = adapter.loss(adapter.prepare(raw), noise, time)
    hook.remove()
    aux = adapter.projector(raw[feature_key("image2")])
    torch.testing.assert_close(seen["aux_visual_inputs"], aux)  # view 1: projected tokens, straight in
    assert seen["vlm_features"].shape == (2, 16 + adapter.config.tokenizer_max_length, 64)  # view 0 + text
    loss.mean().backward()
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in adapter.projector.parameters())


def test_native_control_reproduces_the_ungrafted_policy() -> None:
    native, control = tiny("xvla"), tiny("xvla")
    native.policy.eval(), control.policy.eval()  # X-VLA's transformer has dropout (the native cell runs in eval)
    assert_native_control_reproduces(native, control, 3)


def test_lora_adapts_the_florence_encoder_and_reset_restores_the_policy() -> None:
    adapter = tiny("xvla")
    sha = adapter.policy_sha256
    adapter.graft(GraftProjector(ENC_DIM, adapter.lm_width))
    adapter.add_lora(4)
    trainable = {n for n, p in adapter.policy.named_parameters() if p.requires_grad}
    lora = {n for n in trainable if "lora_" in n}
    assert lora and all(n.startswith("model.vlm.language_model.encoder.layers.") for n in lora)
    report = adapter.freeze_report()
    assert [r.trainable for r in report.rows if r.module in ("vision tower", "action transformer")] == [0, 0]
    adapter.reset()
    assert not adapter.grafted and adapter.policy_sha256 == sha
    from graftcache.backbones.checkpoint import state_dict_sha256

    assert state_dict_sha256(adapter.policy) == sha


def test_saved_tiny_loads_by_hub_id(tmp_path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Saved as lerobot saves a policy, placed in a hub cache snapshot, loaded offline by `org/name`."""
    adapter = tiny("xvla")
    adapter.save(tmp_path / "stage")
    cache = tmp_path / "hub"
    with hub_cache(cache):
        monkeypatch.setenv("HF_HUB_CACHE", str(cache))
        snapshot = publish(tmp_path / "stage", "graftcache-tests/xvla-tiny", cache)
        loaded = load_backbone("xvla", "graftcache-tests/xvla-tiny")
        assert XVLAAdapter.read_token_grid("graftcache-tests/xvla-tiny") == (4, 4)
        assert XVLAAdapter.read_cameras("graftcache-tests/xvla-tiny") == ("image", "image2")
    assert (snapshot / "config.json").is_file() and json.loads((snapshot / "config.json").read_text())["type"] == "xvla"
    assert loaded.policy_sha256 == adapter.policy_sha256 and loaded.random_init
    assert loaded.n_params == adapter.n_params == 528_952  # the tied BART word embedding counted once
    raw = raw_images(adapter, 2)
    noise, _ = fixed_noise_time(adapter, 2)
    torch.testing.assert_close(loaded.predict(loaded.prepare(raw), noise), adapter.predict(adapter.prepare(raw), noise))


def test_released_geometry_on_the_meta_device() -> None:
    """lerobot/xvla-base at LIBERO's 256 px: DaViT /32 -> 8x8 grid, 1 + 64 tokens x 1024 per camera, two
    real views plus none empty, ~0.9B parameters (counted from shapes, nothing allocated)."""
    from lerobot.policies.xvla.modeling_xvla import XVLAPolicy

    from graftcache.backbones.xvla.tiny import xvla_released_config

    config = xvla_released_config(("image", "image2"), 256, 8, 7, "cpu")
    config.device = "meta"
    with torch.device("meta"):
        policy = XVLAPolicy(config)
    adapter = XVLAAdapter(policy, None, None, source="meta", random_init=True)
    params = {name: sum(p.numel() for p in module.parameters()) for name, module in (
        ("tower", policy.model.vlm.vision_tower), ("projector", policy.model.vlm.multi_modal_projector),
        ("bart encoder", policy.model.vlm.language_model), ("transformer", policy.model.transformer))}
    total = sum(p.numel() for p in policy.parameters())
    assert total == sum(params.values()) and 0.85e9 < total < 0.95e9, params
    assert params["tower"] == pytest.approx(360e6, rel=0.05)  # DaViT of Florence-2-large
    assert adapter.token_grid == conv_grid((256, 256), config.get_florence_config().vision_config) == (8, 8)
    assert adapter.lm_width == 1024 == policy.model.vlm.config.text_config.d_model
    hidden = policy.model.vlm.vision_tower(torch.empty(2, 3, 256, 256, device="meta")).last_hidden_state
    tokens = policy.model.vlm.multi_modal_projector(hidden)
    assert tuple(hidden.shape) == (2, 2048, 8, 8) and tuple(tokens.shape) == (2, 1 + 64, 1024)
    assert adapter.max_action_dim == 20 and adapter.chunk_size == 32 and adapter.num_steps == 10
    pixels = {k: torch.empty(2, 3, 256, 256, device="meta") for k in adapter.camera_keys}
    images, masks = policy._prepare_images(pixels)  # both real views, no empty slot in this recipe
    assert tuple(images.shape) == (2, 2, 3, 256, 256) and tuple(masks.shape) == (2, 2)
    assert config.num_image_views == 2 and math.prod(adapter.token_grid) == 64


def test_activation_checkpointing_lowers_the_peak() -> None:
    plain, checkpointed = activation_checkpointing_peaks(grafted("xvla"))
    assert checkpointed < 0.85 * plain, (checkpointed, plain)
