"""EO-1 as a backbone: tiny geometry, the native tower against the policy's own image path (and the merger's
2x2 order), the loss and the sampler against lerobot's `forward` / `predict_action_chunk` under the same random
draws, the graft slots (the image-pad positions of the Qwen sequence), and the released geometry on the meta
device (3.8B parameters are never materialised). The native control, LoRA and reset, save/load by hub id and the
missing base: tests/backbones/test_zoo_common.py."""

from __future__ import annotations

import torch
from helpers.backbones import (
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

from graftcache.backbones.eo1.adapter import EO1Adapter, left_padded
from graftcache.backbones.qwen_vl import merged_grid

SIZE = 128  # the tiny policy's frames (train-tiny's size): smart_resize -> 112 px -> 8x8 patches -> 4x4 tokens


def test_tiny_geometry() -> None:
    adapter = tiny("eo1")
    merger = 32 + (128 * 128 + 128) + (128 * 64 + 64)  # RMSNorm(32), Linear(4 x 32 -> 128), Linear(128 -> 64)
    assert_tiny_zoo_geometry(adapter, 8, merger, 245_800)
    tokenizer = adapter._qwen_processor._processor.tokenizer  # EO-1's 7 tokens added to the tiny vocabulary
    assert len(tokenizer) <= adapter.policy.model.vlm_backbone.config.text_config.vocab_size


def test_native_tower_is_the_policys_own_image_path() -> None:
    """Native tokens equal what Qwen embeds for each camera from lerobot's preprocessed batch, and the patch grid
    is in raster order: regrouped into 2x2 blocks, the merger maps it onto those tokens."""
    adapter = tiny("eo1")
    raw = raw_images(adapter, 3, size=SIZE)
    batch = adapter.prepare(raw)
    qwen = adapter.policy.model.vlm_backbone.model
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
    vision = qwen.visual.config
    assert merged_grid((256, 256), vision.patch_size, vision.spatial_merge_size, 64 * 28 * 28, 128 * 28 * 28) == (9, 9)


def test_loss_and_prediction_are_lerobots_under_the_same_draws() -> None:
    adapter = tiny("eo1")
    adapter.policy.eval()
    raw = raw_images(adapter, 3, size=SIZE)
    batch = adapter.prepare(raw)  # with actions: right-padded prompts (the tasks differ in length)
    assert (batch["attention_mask"][:, -1] == 0).any()
    model = adapter.policy.model
    with torch.no_grad():
        torch.manual_seed(7)
        reference, _ = adapter.policy.forward(dict(batch))
        torch.manual_seed(7)  # modeling_eo1.py draws the time, then the noise
        time = model.sample_time(3, "cpu")
        noise = model.sample_noise((3, adapter.chunk_size, adapter.max_action_dim), "cpu")
        torch.testing.assert_close(adapter._flow_losses(batch, noise, time).mean(), reference)
        inference = adapter.prepare({k: v for k, v in raw.items() if k not in ("action", "action_is_pad")})
        assert (inference["attention_mask"][:, 0] == 0).any()  # lerobot left-pads at inference
        torch.manual_seed(11)
        chunk_ref = adapter.policy.predict_action_chunk(dict(inference))
        torch.manual_seed(11)
        start = model.sample_noise((3, adapter.chunk_size, adapter.max_action_dim), "cpu")
    for key in ("input_ids", "attention_mask", "mm_token_type_ids"):
        torch.testing.assert_close(left_padded(batch)[key], inference[key])
    torch.testing.assert_close(adapter.predict(batch, start), chunk_ref)
    assert chunk_ref.shape == (3, adapter.chunk_size, adapter.action_dim)


def test_graft_fills_the_image_pads_with_projected_features() -> None:
    adapter = grafted("eo1")
    assert {n for n, p in adapter.policy.named_parameters() if p.requires_grad} == {
        f"model.vlm_backbone.model.visual.merger.{p}" for p in ("norm.weight", "norm.bias", "proj.weight", "proj.bias")}
    raw = raw_features(adapter, 2)
    batch = adapter.prepare(raw)
    noise, time = fixed_noise_time(adapter, 2)
    seen, loss = lm_inputs_of_loss(adapter, adapter.policy.model.vlm_backbone.model.language_model, batch, noise, time)
    pads = batch["input_ids"] == adapter.policy.model.vlm_backbone.config.image_token_id
    torch.testing.assert_close(seen["inputs_embeds"][pads], projected_cameras(adapter, raw))
    assert_projector_trained(adapter, loss)
    assert_refuses_odd_token_counts(adapter, raw, noise, time, slots=True)


def test_pooled_features_get_a_prompt_with_their_grid() -> None:
    """The pool-HxW controls: a 2x2 pooled grid gets 4 image pads per camera and the grid_thw of a 2x2 merged image
    (what Qwen's processor writes for a 56 px image), so the projected tokens fill exactly those slots."""
    adapter = grafted("eo1")
    batch = adapter.prepare(pooled_raw(adapter))
    pads = batch["input_ids"] == adapter.policy.model.vlm_backbone.config.image_token_id
    assert pads.sum(dim=1).tolist() == [8, 8] and batch["image_grid_thw"].tolist() == [[1, 4, 4]] * 4
    noise, time = fixed_noise_time(adapter, 2)
    assert torch.isfinite(adapter.loss(batch, noise, time)).all()
    assert adapter._qwen_processor.image_max_pixels == 16 * 28 * 28  # the bounds are the policy's again


def test_released_geometry_on_the_meta_device() -> None:
    """lerobot/eo1-base at LIBERO's 256 px: Qwen2.5-VL-3B (ViT 1280 x 32 blocks, merger into the 2048-wide,
    36-layer LM), 9x9 = 81 tokens per camera, ~3.77B parameters (counted from shapes, nothing allocated). The
    prompt's image pads come from lerobot's own processor steps at the released pixel bounds (the image
    processor is Qwen2-VL's defaults, the same in the tiny folder)."""
    from lerobot.policies.eo1.processor_eo1 import make_eo1_pre_post_processors

    from graftcache.backbones.eo1.tiny import QWEN_VL_DIR, construct, eo1_released_config

    config = eo1_released_config(("image", "image2"), 256, 8, 7, "cpu")
    config.device = "meta"
    with torch.device("meta"):
        policy = construct(config)
    adapter = EO1Adapter(policy, None, None, source="meta", random_init=True)
    qwen = policy.model.vlm_backbone.model
    params = {name: sum(p.numel() for p in m.parameters()) for name, m in (
        ("vit", qwen.visual), ("merger", qwen.visual.merger), ("lm", qwen.language_model), ("eo1", policy))}
    assert params["vit"] == 668_684_288 and params["merger"] == 36_708_608 and params["lm"] == 3_085_938_688
    assert params["eo1"] == adapter.n_params == 3_771_607_072, params
    assert adapter.token_grid == (9, 9) and adapter.lm_width == 2048
    assert qwen.visual.merger.mlp[-1].out_features == 2048
    assert adapter.max_action_dim == 32 and adapter.chunk_size == 16 and adapter.num_steps == 10
    assert {p.dtype for p in qwen.parameters()} == {torch.bfloat16}
    config.vlm_base, config.device = str(QWEN_VL_DIR), "cpu"
    pre, _ = make_eo1_pre_post_processors(config, dataset_stats=lowdim_stats())
    raw = {k: torch.rand(2, 3, 256, 256) for k in adapter.camera_keys}
    batch = pre({**raw, "observation.state": torch.zeros(2, 8), "task": ["open the drawer", "put the bowl"]})
    assert batch["image_grid_thw"].tolist() == [[1, 18, 18]] * 4  # 252 px: 18x18 patches -> 2x2 merge -> 9x9
    pads = batch["mm_token_type_ids"] == 1  # the tiny tokenizer's own image-pad id marks the slots
    assert pads.sum(dim=1).tolist() == [2 * 81, 2 * 81]
