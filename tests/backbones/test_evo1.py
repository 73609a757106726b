"""EVO1 as a backbone: tiny geometry, the native tower against the policy's own image path (CLS dropped, pixel
shuffle, projector), the loss and the sampler against lerobot's `forward` / `predict_action_chunk` under the same
random draws, the graft slots (the `<IMG_CONTEXT>` positions of the InternVL prompt), pooled grids, and the
released geometry on the meta device (nothing of the ~0.8B parameters is materialised). The native control, LoRA
and reset, save/load by hub id and the missing base: tests/backbones/test_zoo_common.py."""

from __future__ import annotations

import pytest
import torch
from helpers.backbones import (
    ENC_DIM,
    assert_projector_trained,
    assert_tiny_zoo_geometry,
    fixed_noise_time,
    grafted,
    raw_features,
    raw_images,
    tiny,
)

from graftcache.backbones.evo1.adapter import Evo1Adapter
from graftcache.errors import BackboneError
from graftcache.graft import feature_key

SIZE = 128  # the tiny policy's frames (train-tiny's size): resized to 112 px -> 8x8 patches -> 4x4 tokens


def _lm_inputs(adapter, batch: dict, noise, time) -> tuple[torch.Tensor, dict, torch.Tensor]:
    """The `<IMG_CONTEXT>` positions of the prompt InternVL receives, the language model's inputs (forward
    pre-hooks) during one loss, and the loss."""
    ids, seen = {}, {}
    internvl = adapter._vision_owner
    hooks = [internvl.register_forward_pre_hook(lambda m, args, kwargs: ids.update(kwargs), with_kwargs=True),
             internvl.language_model.register_forward_pre_hook(lambda m, args, kwargs: seen.update(kwargs),
                                                               with_kwargs=True)]
    try:
        loss = adapter.loss(batch, noise, time)
    finally:
        for hook in hooks:
            hook.remove()
    return ids["input_ids"] == internvl.config.image_token_id, seen, loss


def test_tiny_geometry() -> None:
    adapter = tiny("evo1")
    assert len(adapter._vision_owner.language_model.layers) == 2  # the tiny LM's 3 layers cut as lerobot cuts
    projector = 2 * 128 + (128 * 64 + 64) + (64 * 64 + 64)  # LayerNorm(4 x 32), Linear(128, 64), Linear(64, 64)
    assert "other" not in assert_tiny_zoo_geometry(adapter, 8, projector, 354_800)
    noise = adapter._uniform(adapter.sample_noise(1000, torch.Generator().manual_seed(0)))  # EVO1's start noise
    quartiles = torch.quantile(noise.flatten(), torch.tensor([0.25, 0.5, 0.75]))
    assert noise.abs().max() <= 1 and torch.allclose(quartiles, torch.tensor([-0.5, 0.0, 0.5]), atol=0.01)


def test_native_tower_is_the_policys_own_image_path() -> None:
    """Native tokens equal what InternVL scatters into each camera's slots from the policy's own batch, and the
    patch grid is the tower's (CLS dropped) in raster order: pixel-shuffled and projected, it gives those tokens."""
    adapter = tiny("evo1")
    raw = raw_images(adapter, 3, size=SIZE)
    batch = adapter.prepare(raw)
    internvl = adapter._vision_owner
    seen = []
    hook = internvl.multi_modal_projector.register_forward_hook(lambda m, args, out: seen.append(out))
    noise, time = fixed_noise_time(adapter, 3)
    with torch.no_grad():
        adapter.loss(batch, noise, time)
    hook.remove()
    own = seen[0].view(3, 3, 16, 64)  # sample after sample, view after view (the third view: zero padding)
    for i, key in enumerate(adapter.camera_keys):
        torch.testing.assert_close(adapter.native_tokens(raw[key]), own[:, i])
    grid = adapter.native_patch_grid(raw[adapter.camera_keys[0]])
    with torch.no_grad():
        shuffled = internvl.pixel_shuffle(grid, scale_factor=0.5).reshape(3, 16, 128)
        torch.testing.assert_close(internvl.multi_modal_projector(shuffled), own[:, 0])


def test_loss_and_prediction_are_lerobots_under_the_same_draws() -> None:
    adapter = tiny("evo1")
    adapter.policy.eval()
    raw = raw_images(adapter, 3, size=SIZE)
    batch = adapter.prepare(raw)
    with torch.no_grad():
        torch.manual_seed(7)
        reference, _ = adapter.policy.forward(dict(batch), reduction="none")
        torch.manual_seed(7)  # flow_matching.py draws the time, then the noise
        t = torch.distributions.Beta(2, 2).sample((3,)).clamp(0.02, 0.98)
        noise = torch.rand(3, adapter.chunk_size, adapter.max_action_dim) * 2 - 1
        # graftcache's noise is standard normal (EVO1's uniform through the inverse normal CDF), its time the noise
        # level (EVO1's t = 1 - time)
        ours = adapter.loss(batch, torch.erfinv(noise) * 2 ** 0.5, 1 - t)
        torch.manual_seed(11)
        chunk_ref = adapter.policy.predict_action_chunk(dict(batch))
        torch.manual_seed(11)
        start = torch.rand(3, adapter.chunk_size * adapter.max_action_dim) * 2 - 1
    torch.testing.assert_close(ours, reference)
    chunk = adapter.predict(batch, torch.erfinv(start).view(3, adapter.chunk_size, adapter.max_action_dim) * 2 ** 0.5)
    torch.testing.assert_close(chunk, chunk_ref[:, :, : adapter.action_dim])
    assert chunk.shape == (3, adapter.chunk_size, adapter.action_dim)
    torch.testing.assert_close(adapter.unnormalize(chunk), adapter.postprocessor(chunk_ref))  # raw units, 7 dims


def test_graft_fills_the_image_context_slots_with_projected_features() -> None:
    adapter = grafted("evo1")
    assert {n for n, p in adapter.policy.named_parameters() if p.requires_grad} == {
        f"model.embedder.model.multi_modal_projector.{p}"
        for p in ("norm.weight", "norm.bias", "proj.weight", "proj.bias")}
    raw = raw_features(adapter, 2)
    batch = adapter.prepare(raw)
    noise, time = fixed_noise_time(adapter, 2)
    pads, seen, loss = _lm_inputs(adapter, batch, noise, time)
    assert pads.sum(dim=1).tolist() == [3 * 16, 3 * 16]
    cameras = [raw[feature_key(k)] for k in adapter.camera_keys]
    views = torch.stack([*cameras, torch.zeros_like(cameras[0])], dim=1)  # the third view: zeros, masked out
    expected = adapter.projector(views.flatten(0, 2))
    torch.testing.assert_close(seen["inputs_embeds"][pads], expected)
    attended = seen["attention_mask"].bool() & pads
    assert attended.sum(dim=1).tolist() == [2 * 16, 2 * 16]  # the padded view's slots are masked
    assert_projector_trained(adapter, loss)
    with pytest.raises(BackboneError, match="different token counts"):
        adapter.loss(adapter.prepare({**raw, feature_key("image"): raw[feature_key("image")][:, :9]}), noise, time)


def test_stage1_checkpoints_still_train_the_graft() -> None:
    """A stage-1 EVO1 embeds without gradients (`_compute_fused_tokens` under no_grad); grafted, the projector
    still gets them."""
    adapter = grafted("evo1")
    adapter.config.finetune_vlm = adapter.config.finetune_language_model = False
    adapter.config.finetune_vision_model = False
    assert not adapter.policy._tracks_vlm_gradients
    batch = adapter.prepare(raw_features(adapter, 2))
    adapter.loss(batch, *fixed_noise_time(adapter, 2)).mean().backward()
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in adapter.projector.parameters())


def test_pooled_features_get_as_many_slots_as_tokens() -> None:
    """The pool-HxW controls: a 2x2 pooled grid gets 4 `<IMG_CONTEXT>` slots per view, which its projected tokens
    fill exactly; the embedder's own count is restored afterwards."""
    adapter = grafted("evo1")
    raw = {**raw_features(adapter, 2), **{feature_key(k): torch.randn(2, 4, ENC_DIM) for k in adapter.camera_keys}}
    noise, time = fixed_noise_time(adapter, 2)
    pads, seen, loss = _lm_inputs(adapter, adapter.prepare(raw), noise, time)
    assert torch.isfinite(loss).all() and pads.sum(dim=1).tolist() == [3 * 4, 3 * 4]
    cameras = [raw[feature_key(k)] for k in adapter.camera_keys]
    expected = adapter.projector(torch.stack([*cameras, torch.zeros_like(cameras[0])], dim=1).flatten(0, 2))
    torch.testing.assert_close(seen["inputs_embeds"][pads], expected)
    assert adapter.policy.model.embedder.num_image_token == 16


def test_released_geometry_on_the_meta_device(tmp_path) -> None:
    """lerobot's EVO1 defaults at LIBERO's 256 px: InternVL3-1B-hf (InternViT-300M at 448 px, 32x32 patches ->
    pixel shuffle -> 16x16 = 256 tokens per camera, projector into the 896-wide Qwen2.5 LM cut to 14 of its 24
    layers), counted from shapes on the meta device. The prompt's slots come from lerobot's own prompt builder
    and tokenizer call (a folder with the released config.json and the tiny tokenizer)."""
    from graftcache.backbones.evo1.tiny import INTERNVL3_1B, construct, evo1_released_config, write_internvl

    folder = write_internvl(tmp_path / "internvl3-1b", INTERNVL3_1B)
    config = evo1_released_config(("image", "image2"), 256, 8, 7, "cpu", vlm=str(folder))
    config.device = "meta"
    with torch.device("meta"):
        policy = construct(config)
    adapter = Evo1Adapter(policy, None, None, source="meta", random_init=True)
    internvl = adapter._vision_owner
    params = {name: sum(p.numel() for p in m.parameters()) for name, m in (
        ("vit", internvl.vision_tower), ("projector", internvl.multi_modal_projector),
        ("lm", internvl.language_model), ("head", policy.model.action_head), ("evo1", policy))}
    assert params["projector"] == 2 * 4096 + (4096 * 896 + 896) + (896 * 896 + 896)
    assert len(internvl.language_model.layers) == 14 and internvl.language_model.embed_tokens.weight.shape == (
        151674, 896)
    assert params == {"vit": 304_012_288, "projector": 4_482_816, "lm": 344_674_176, "head": 122_029_360,
                      "evo1": 775_198_640}
    assert adapter.n_params == 775_198_640
    assert adapter.token_grid == (16, 16) and adapter.lm_width == 896 and adapter.embed_scale == 1.0
    assert adapter.max_action_dim == 24 and adapter.chunk_size == 50 and adapter.num_steps == 32
    assert {p.dtype for p in internvl.parameters()} == {torch.bfloat16}
    embedder = policy.model.embedder
    assert embedder.num_image_token == 256 and embedder.image_size == 448 and config.max_views == 3
    prompts = embedder._build_multimodal_prompts([[1, 1, 1]] * 2, ["open the drawer", "put the bowl"])
    ids = embedder.tokenizer(prompts, return_tensors="pt", padding=True)["input_ids"]
    assert (ids == embedder.img_context_token_id).sum(dim=1).tolist() == [3 * 256, 3 * 256]
