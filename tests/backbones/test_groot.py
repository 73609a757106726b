"""GR00T N1.7 as a backbone: tiny geometry, the native tower against the policy's own image path (and the merger's
2x2 order), the loss and the sampler against lerobot's `forward` / `predict_action_chunk` under the same random
draws, the graft slots (the image-pad positions of the Qwen3-VL sequence, no deepstack features), the native
control without deepstack, the missing base model, and the released geometry on the meta device (3.1B parameters
are never materialised). LoRA and reset, save/load by hub id: tests/backbones/test_zoo_common.py."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import pytest
import torch
from helpers.backbones import (
    assert_native_control_reproduces,
    assert_projector_trained,
    assert_refuses_odd_token_counts,
    assert_tiny_zoo_geometry,
    fixed_noise_time,
    grafted,
    lm_inputs_of_loss,
    lowdim_stats,
    pooled_raw,
    projected_cameras,
    raw_features,
    raw_images,
    tiny,
)

from graftcache.backbones import load_backbone
from graftcache.backbones.groot.adapter import PADDED_ACTION, GrootAdapter
from graftcache.backbones.qwen_vl import merged_grid
from graftcache.errors import BackboneError

SIZE = 128  # the tiny policy's frames; GR00T's VLM step resizes to 128 px anyway: 8x8 patches -> 4x4 tokens


def _qwen(adapter):
    return adapter.policy._groot_model.backbone.model.model


@contextlib.contextmanager
def no_deepstack(adapter) -> Iterator[None]:
    """The ViT with its deepstack mergers switched off (what a graft leaves the LM: no deepstack features)."""
    visual = _qwen(adapter).visual
    saved, visual.deepstack_visual_indexes = visual.deepstack_visual_indexes, []
    try:
        yield
    finally:
        visual.deepstack_visual_indexes = saved


def test_tiny_geometry() -> None:
    from lerobot.policies.groot.groot_n1_7 import GR00TN17

    own = GR00TN17.__dict__["from_pretrained"]
    adapter = tiny("groot")
    assert GR00TN17.__dict__["from_pretrained"] is own  # lerobot's loader is back after construction
    assert adapter.num_steps == 4 and len(_qwen(adapter).language_model.layers) == 2  # cut at select_layer
    merger = 2 * 32 + (128 * 128 + 128) + (128 * 64 + 64)  # LayerNorm(32), Linear(4 x 32 -> 128), Linear(128 -> 64)
    assert_tiny_zoo_geometry(adapter, 8, merger, 810_496)
    tokenizer = adapter._vlm_step.proc.tokenizer
    assert len(tokenizer) <= _qwen(adapter).config.text_config.vocab_size


def test_native_tower_is_the_policys_own_image_path() -> None:
    """Native tokens equal what Qwen embeds for each camera from lerobot's preprocessed batch, and the patch grid
    is in raster order: regrouped into 2x2 blocks, the merger maps it onto those tokens."""
    adapter = tiny("groot")
    raw = raw_images(adapter, 3, size=96)  # any frame size: GR00T's step resizes it to 128 px
    batch = adapter.prepare(raw)
    qwen = _qwen(adapter)
    assert (batch["input_ids"] == qwen.config.image_token_id).sum(dim=1).tolist() == [2 * 16] * 3
    with torch.no_grad():
        own = torch.stack(qwen.get_image_features(batch["pixel_values"], batch["image_grid_thw"]).pooler_output)
    own = own.view(3, 2, 16, 64)  # images in the prompt: sample after sample, camera after camera
    for i, key in enumerate(adapter.camera_keys):
        torch.testing.assert_close(adapter.native_tokens(raw[key]), own[:, i])
    grid = adapter.native_patch_grid(raw[adapter.camera_keys[0]])
    blocks = grid.view(3, 4, 2, 4, 2, 32).permute(0, 1, 3, 2, 4, 5).reshape(-1, 32)
    with torch.no_grad():
        torch.testing.assert_close(qwen.visual.merger(blocks).view(3, 16, 64), own[:, 0])
    assert merged_grid((256, 256), 16, 2, 65536, 16777216) == (8, 8)
    assert merged_grid((128, 128), 16, 2, 65536, 16777216) == (8, 8)


def test_loss_and_prediction_are_lerobots_under_the_same_draws() -> None:
    adapter = tiny("groot")
    adapter.policy.eval()
    batch = adapter.prepare(raw_images(adapter, 3, size=SIZE))
    head = adapter.policy._groot_model.action_head
    shape = (3, adapter.chunk_size, adapter.max_action_dim)
    with torch.no_grad():
        assert batch["action"].shape == (3, 10, 7) and batch[PADDED_ACTION].shape == (3, 10, 8)
        torch.testing.assert_close(batch[PADDED_ACTION][..., :7], batch["action"])
        assert not batch[PADDED_ACTION][..., 7:].any()
        torch.manual_seed(7)
        reference, _ = adapter.policy.forward({**batch, "action": batch[PADDED_ACTION]})
        torch.manual_seed(7)  # groot_n1_7.py draws the noise, then the time
        noise = torch.randn(shape)
        time = head.sample_time(3, torch.device("cpu"), torch.float32)  # GR00T's: 1 is the action
        mask = batch["action_mask"]
        error = adapter._flow_losses(batch, noise, 1 - time)  # graftcache's: 1 is pure noise
        torch.testing.assert_close((error * mask).sum() / (mask.sum() + 1e-6), reference)
        inference = {k: v for k, v in batch.items() if k not in ("action", "action_is_pad", PADDED_ACTION)}
        torch.manual_seed(11)
        chunk_ref = adapter.policy.predict_action_chunk(dict(inference))
        torch.manual_seed(11)
        start = torch.randn(shape)
    torch.testing.assert_close(adapter.predict(batch, start), chunk_ref)
    assert chunk_ref.shape == (3, adapter.chunk_size, adapter.action_dim)
    drawn = r"groot: noise of shape \(3, 4, 8\) given, \(3, 10, 8\) drawn by torch.randn in lerobot.policies.groot"
    with pytest.raises(BackboneError, match=drawn + r".groot_n1_7"):
        adapter.predict(batch, start[:, :4])


def test_time_one_is_pure_noise_as_in_fit() -> None:
    """graftcache's flow time (graftcache.fit.loop.flow_time, the pi0 family's: 1 is pure noise) is GR00T's 1 - t:
    at time 1 the action head is fed the noise itself, at time 0 the (normalised, padded) action."""
    adapter = tiny("groot")
    adapter.policy.eval()
    batch = adapter.prepare(raw_images(adapter, 2, size=SIZE))
    noise, _ = fixed_noise_time(adapter, 2)
    fed = []
    encoder = adapter.policy._groot_model.action_head.action_encoder
    hook = encoder.register_forward_pre_hook(lambda m, args: fed.append(args[0]))
    with torch.no_grad():
        adapter.loss(batch, noise, torch.ones(2))
        adapter.loss(batch, noise, torch.zeros(2))
    hook.remove()
    torch.testing.assert_close(fed[0], noise)
    torch.testing.assert_close(fed[1], batch[PADDED_ACTION])


def test_graft_fills_the_image_pads_with_projected_features_and_no_deepstack() -> None:
    adapter = grafted("groot")
    assert {n for n, p in adapter.policy.named_parameters() if p.requires_grad} == {
        f"_groot_model.backbone.model.model.visual.merger.{p}"
        for p in ("norm.weight", "norm.bias", "proj.weight", "proj.bias")}
    raw = raw_features(adapter, 2)
    batch = adapter.prepare(raw)
    noise, time = fixed_noise_time(adapter, 2)
    seen, loss = lm_inputs_of_loss(adapter, _qwen(adapter).language_model, batch, noise, time)
    pads = batch["input_ids"] == _qwen(adapter).config.image_token_id
    expected = projected_cameras(adapter, raw)  # image, image2: also the video's sorted order
    torch.testing.assert_close(seen["inputs_embeds"][pads], expected)
    assert seen["deepstack_visual_embeds"] is None and torch.equal(seen["visual_pos_masks"], pads)
    assert_projector_trained(adapter, loss)
    assert_refuses_odd_token_counts(adapter, raw, noise, time, slots=True)


def test_pooled_features_get_a_prompt_with_their_grid() -> None:
    """The pool-HxW controls: a 2x2 pooled grid gets 4 image pads per camera and the grid_thw of a 2x2 merged image
    (what Qwen's processor writes for a 64 px frame), so the projected tokens fill exactly those slots."""
    adapter = grafted("groot")
    batch = adapter.prepare(pooled_raw(adapter))
    pads = batch["input_ids"] == _qwen(adapter).config.image_token_id
    assert pads.sum(dim=1).tolist() == [8, 8] and batch["image_grid_thw"].tolist() == [[1, 4, 4]] * 4
    noise, time = fixed_noise_time(adapter, 2)
    assert torch.isfinite(adapter.loss(batch, noise, time)).all()
    step = adapter._vlm_step  # the step and the processor are the policy's again
    assert step.image_target_size == [128, 128] and step.image_crop_size == [115, 115]
    assert step.proc.image_processor.size["shortest_edge"] == 4 * 32 * 32


def test_native_control_reproduces_the_policy_without_deepstack() -> None:
    """The cached native tokens through the identity projector give the ungrafted policy's loss and chunk with its
    deepstack switched off (a graft has none); with deepstack the tiny policy computes something else."""
    native, control = tiny("groot"), tiny("groot")
    raw = raw_images(native, 2, size=SIZE)
    noise, time = fixed_noise_time(native, 2)
    with torch.no_grad():
        with_deepstack = native.loss(native.prepare(raw), noise, time)
        with no_deepstack(native):
            without = native.loss(native.prepare(raw), noise, time)
    assert not torch.allclose(with_deepstack, without)
    with no_deepstack(native):
        assert_native_control_reproduces(native, control, 2, size=SIZE)


def test_missing_base_model_is_one_line(tmp_path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A (non-tiny) checkpoint whose base model (nvidia/GR00T-N1.7-3B) is not in the HF cache: one line naming it."""
    folder = tiny("groot").save(tmp_path / "policy")
    (folder / "graftcache_tiny.json").unlink()
    config = (folder / "config.json").read_text()
    (folder / "config.json").write_text(config.replace(str(GrootAdapter._vlm_folder({"backbone": "groot"})),
                                                       "nvidia/GR00T-N1.7-3B"))
    monkeypatch.setenv("HF_HUB_CACHE", str(tmp_path / "empty"))
    with pytest.raises(BackboneError, match="GR00T's base model config 'nvidia/GR00T-N1.7-3B' is neither"):
        load_backbone("groot", folder)


@pytest.mark.slow
def test_released_geometry_on_the_meta_device() -> None:
    """nvidia/GR00T-N1.7-3B at LIBERO's 256 px: Cosmos-Reason2-2B's Qwen3-VL (ViT 1024 x 24 blocks + 3 deepstack
    mergers, merger into the 2048-wide LM cut at 16 of 28 layers) and the 1.6B-parameter DiT head, 8x8 = 64 tokens
    per camera, ~3.14B parameters (counted from shapes, nothing allocated). The prompt's image pads come from
    lerobot's own processor steps at Qwen3-VL-2B's pixel bounds."""
    from lerobot.policies.groot.processor_groot import make_groot_pre_post_processors

    from graftcache.backbones.groot.construct import construct, groot_released_config, released_base_config
    from graftcache.backbones.groot.tiny import GROOT_DIR
    from graftcache.backbones.lean_load import construct as on_meta
    from graftcache.backbones.tiny_assets import QWEN3_VL_PIXELS

    config = groot_released_config(("image", "image2"), 256, 8, 7, "cpu")
    policy = on_meta(lambda: construct(config, released_base_config()), config)
    adapter = GrootAdapter(policy, None, None, source="meta", random_init=True)
    groot = policy._groot_model
    qwen = groot.backbone.model.model
    params = {name: sum(p.numel() for p in m.parameters()) for name, m in (
        ("vit", qwen.visual), ("merger", qwen.visual.merger), ("lm", qwen.language_model),
        ("head", groot.action_head), ("groot", policy))}
    assert params["vit"] == 406_957_056 and params["merger"] == 25_174_016 and params["lm"] == 1_116_542_976
    assert params["head"] == 1_620_515_968 and params["groot"] == adapter.n_params == 3_144_016_000, params
    assert {p.device.type for p in policy.parameters()} == {"meta"}
    assert len(qwen.language_model.layers) == 16 and qwen.visual.deepstack_visual_indexes == [5, 11, 17]
    assert adapter.token_grid == (8, 8) and adapter.lm_width == 2048
    assert qwen.visual.merger.linear_fc2.out_features == 2048
    assert adapter.max_action_dim == 132 and adapter.chunk_size == 40 and adapter.num_steps == 4
    pre, _ = make_groot_pre_post_processors(config, dataset_stats=lowdim_stats())
    step = next(s for s in pre.steps if type(s).__name__ == "GrootN17VLMEncodeStep")
    assert step.image_target_size == [256, 256] and step.image_crop_size == [230, 230]
    step.model_name = str(GROOT_DIR)  # the tiny tokenizer, at Qwen3-VL-2B's pixel bounds
    step.proc.image_processor.size = {"shortest_edge": QWEN3_VL_PIXELS[0], "longest_edge": QWEN3_VL_PIXELS[1]}
    raw = {k: torch.rand(2, 3, 256, 256) for k in adapter.camera_keys}
    batch = pre({**raw, "observation.state": torch.zeros(2, 8), "task": ["open the drawer", "put the bowl"]})
    assert batch["image_grid_thw"].tolist() == [[1, 16, 16]] * 4  # 256 px: 16x16 patches -> 2x2 merge -> 8x8
    pads = batch["mm_token_type_ids"] == 1
    assert pads.sum(dim=1).tolist() == [2 * 64, 2 * 64]
