"""VLA-JEPA as a backbone: tiny geometry, the native tower against the policy's own image path (and the merger's
2x2 order), the action loss and the sampler against lerobot's `forward` / `predict_action_chunk` under the same
random draws, the graft slots (the image-pad positions of the Qwen3-VL prompt, no deepstack), the native control
without deepstack, and the released geometry on the meta device (2.3B parameters are never materialised). LoRA
and reset, save/load by hub id and the missing base: tests/backbones/test_zoo_common.py."""

from __future__ import annotations

import json
from unittest import mock

import pytest
import torch
from helpers.backbones import (
    ENC_DIM,
    assert_native_control_reproduces,
    assert_projector_trained,
    assert_refuses_odd_token_counts,
    assert_tiny_zoo_geometry,
    fixed_noise_time,
    grafted,
    lm_inputs_of_loss,
    pooled_raw,
    projected_cameras,
    raw_features,
    raw_images,
    tiny,
)
from helpers.memory import peak_tensor_bytes

from graftcache.backbones import lean_load
from graftcache.backbones.qwen_vl import merged_grid
from graftcache.backbones.vla_jepa.adapter import VLAJEPAAdapter
from graftcache.errors import BackboneError
from graftcache.fit.controls import PassThroughProjector
from graftcache.graft import feature_key

SIZE = 128  # the tiny policy's frames (train-tiny's size): 8x8 patches of 16 px -> 4x4 merged tokens


def _cameras_tokens(adapter, batch: dict) -> tuple[dict, torch.Tensor]:
    """The policy's own Qwen inputs for a prepared batch and the image tokens Qwen embeds from them, [B, cams, T,
    D] (images in the prompt: sample after sample, camera after camera)."""
    from lerobot.policies.vla_jepa.modeling_vla_jepa import _get_autocast_context

    model = adapter.policy.model
    inputs = model.qwen.build_inputs(adapter.policy._prepare_model_inputs(batch, training=False)["images"],
                                     batch["task"], model.replace_prompt, model.embodied_replace_prompt)
    qwen = adapter._qwen
    with torch.no_grad(), _get_autocast_context("cpu"):
        own = torch.stack(qwen.get_image_features(inputs["pixel_values"], inputs["image_grid_thw"]).pooler_output)
    return inputs, own.view(len(batch["task"]), len(adapter.camera_keys), *own.shape[1:])


def test_tiny_geometry() -> None:
    adapter = tiny("vla_jepa")
    assert not adapter.config.enable_world_model and adapter.policy.model.video_predictor is None
    merger = 2 * 32 + (128 * 128 + 128) + (128 * 64 + 64)  # LayerNorm(32), Linear(4 x 32 -> 128), Linear(128 -> 64)
    report = assert_tiny_zoo_geometry(adapter, 7, merger, 295_927)
    assert report["deepstack mergers"] == 2 * 128 + (128 * 128 + 128) + (128 * 64 + 64)  # one, LayerNorm after 2x2
    tokenizer = adapter.policy.model.qwen.processor.tokenizer  # 40 action tokens + the embodied one added
    assert len(tokenizer) <= adapter._qwen.config.text_config.vocab_size


def test_native_tower_is_the_policys_own_image_path() -> None:
    """Native tokens equal what Qwen embeds for each camera from the policy's own prompt inputs, and the patch grid
    is in raster order: regrouped into 2x2 blocks, the merger maps it onto those tokens."""
    adapter = tiny("vla_jepa")
    raw = raw_images(adapter, 3, size=SIZE)
    inputs, own = _cameras_tokens(adapter, adapter.prepare(raw))
    assert (inputs["input_ids"] == adapter._qwen.config.image_token_id).sum(dim=1).tolist() == [2 * 16] * 3
    for i, key in enumerate(adapter.camera_keys):
        torch.testing.assert_close(adapter.native_tokens(raw[key]), own[:, i].float())
    grid = adapter.native_patch_grid(raw[adapter.camera_keys[0]])
    blocks = grid.view(3, 4, 2, 4, 2, 32).permute(0, 1, 3, 2, 4, 5).reshape(-1, 32)
    with torch.no_grad():
        merged = adapter._vision_owner.merger(blocks).view(3, 16, 64)
    torch.testing.assert_close(merged, own[:, 0].float(), atol=0.02, rtol=0.02)  # the policy's merger ran in bf16
    assert merged_grid((256, 256), 16, 2, 65536, 16777216) == (8, 8)
    assert merged_grid((480, 640), 16, 2, 65536, 16777216) == (15, 20)


def test_loss_and_prediction_are_lerobots_under_the_same_draws() -> None:
    """One noise draw per sample (repeated_diffusion_steps 1): graftcache's masked loss is lerobot's `action_loss`
    from the same noise and t (t = 1 - graftcache's time), and the predicted chunk lerobot's from the same noise."""
    adapter = tiny("vla_jepa")
    adapter.policy.eval()
    raw = raw_images(adapter, 3, size=SIZE)
    batch = adapter.prepare(raw)
    head = adapter.policy.model.action_model
    adapter.config.repeated_diffusion_steps = 1
    with torch.no_grad():
        torch.manual_seed(7)
        reference, logs = adapter.policy.forward(dict(batch))
        torch.manual_seed(7)  # action_head.py draws the noise, then t
        noise = torch.randn(3, adapter.chunk_size, adapter.action_dim)
        t = head.sample_time(3, torch.device("cpu"), torch.float32)
        error = adapter._flow_losses(batch, noise, 1 - t)
        valid = ~batch["action_is_pad"]
        torch.testing.assert_close(error[valid].mean(), reference)
        assert logs["wm_loss"] == 0.0  # no world model: the policy's loss is its action loss
        inference = {k: v for k, v in batch.items() if k not in ("action", "action_is_pad")}
        torch.manual_seed(11)
        chunk_ref = adapter.policy.predict_action_chunk(dict(inference))
        torch.manual_seed(11)
        start = torch.randn(3, adapter.chunk_size, adapter.action_dim)
    torch.testing.assert_close(adapter.predict(batch, start), chunk_ref)
    assert chunk_ref.shape == (3, adapter.chunk_size, adapter.action_dim)
    assert not torch.equal(adapter.predict(batch, start, num_steps=1), chunk_ref)  # the step count is honoured
    drawn = r"vla_jepa: noise of shape \(3, 10, 8\) given, \(3, 10, 7\) drawn by torch.randn_like"
    with pytest.raises(BackboneError, match=drawn):
        adapter.loss(batch, torch.zeros(3, 10, 8), 1 - t)


def test_loss_masks_padded_steps_per_sample_and_ignores_batch_mates() -> None:
    """Padded steps are masked per sample, and a sample's loss does not depend on the other prompts of its batch
    (they set its left padding): what lets cells share a backbone pass (spec loss_per_sample)."""
    adapter = tiny("vla_jepa")
    adapter.policy.eval()
    raw = raw_images(adapter, 3, size=SIZE)
    batch = adapter.prepare(raw)
    noise, time = fixed_noise_time(adapter, 3)
    with torch.no_grad():
        error = adapter._flow_losses(batch, noise, time)
        loss = adapter.loss(batch, noise, time)
        alone = adapter.prepare({k: v[2:] for k, v in raw.items()})  # the shortest task: no padding alone
        single = adapter.loss(alone, noise[2:], time[2:])
    torch.testing.assert_close(loss, torch.stack([error[0, :-3].mean(), error[1].mean(), error[2].mean()]))
    assert adapter.spec.loss_per_sample
    torch.testing.assert_close(single, loss[2:], atol=1e-3, rtol=1e-2)  # Qwen runs under bf16 autocast


def test_graft_fills_the_image_pads_with_projected_features_and_no_deepstack() -> None:
    adapter = grafted("vla_jepa")
    assert {n for n, p in adapter.policy.named_parameters() if p.requires_grad} == {
        f"model.qwen.model.model.visual.merger.{p}" for p in ("norm.weight", "norm.bias", "proj.weight", "proj.bias")}
    raw = raw_features(adapter, 2)
    batch = adapter.prepare(raw)
    noise, time = fixed_noise_time(adapter, 2)
    seen, loss = lm_inputs_of_loss(adapter, adapter._qwen.language_model, batch, noise, time)
    pads = seen["visual_pos_masks"]
    expected = projected_cameras(adapter, raw)
    assert pads.sum(dim=1).tolist() == [2 * 16, 2 * 16] and seen["deepstack_visual_embeds"] == []
    torch.testing.assert_close(seen["inputs_embeds"][pads].float(), expected, atol=0.02, rtol=0.02)  # bf16 autocast
    assert_projector_trained(adapter, loss)
    assert_refuses_odd_token_counts(adapter, raw, noise, time)


def test_pooled_features_get_a_prompt_with_their_grid() -> None:
    """The pool-HxW controls: a 2x2 pooled grid gets 4 image pads per camera and the grid_thw of a 2x2 merged image
    (what Qwen's processor writes for a 64 px image), so the projected tokens fill exactly those slots."""
    adapter = grafted("vla_jepa")
    batch = adapter.prepare(pooled_raw(adapter))
    model = adapter.policy.model
    inputs = model.qwen.build_inputs(adapter.policy._prepare_model_inputs(batch)["images"], batch["task"],
                                     model.replace_prompt, model.embodied_replace_prompt)
    pads = inputs["input_ids"] == adapter._qwen.config.image_token_id
    assert pads.sum(dim=1).tolist() == [8, 8] and inputs["image_grid_thw"].tolist() == [[1, 4, 4]] * 4
    assert inputs["pixel_values"].shape == (2 * 2 * 4, ENC_DIM)
    noise, time = fixed_noise_time(adapter, 2)
    assert torch.isfinite(adapter.loss(batch, noise, time)).all()
    assert model.qwen.processor.image_processor.size.longest_edge == 16 * 32 * 32  # the bounds are the policy's again


def test_native_control_reproduces_the_ungrafted_policy_without_deepstack() -> None:
    """The native control (the policy's own merger tokens through an identity projector) is the ungrafted policy
    minus its deepstack additions: exact with those switched off, different with them on."""
    native = tiny("vla_jepa")
    native._vision_owner.deepstack_visual_indexes = []
    assert_native_control_reproduces(native, tiny("vla_jepa"), 3, size=SIZE)
    with_deepstack, control = tiny("vla_jepa"), tiny("vla_jepa")
    with pytest.raises(AssertionError, match="not close"):
        assert_native_control_reproduces(with_deepstack, control, 3, size=SIZE)


def test_resize_images_to_sets_the_grid_the_native_tower_and_the_grafted_prompt() -> None:
    """A checkpoint with `resize_images_to` (converted VLA-JEPA checkpoints set the training resolution there):
    `predict_action` resizes frames to it, so the token grid, the native tokens and the grafted prompt follow it
    (96 px -> 6x6 patches -> 3x3 tokens in the tiny processor), and the grafted sampler does not resize features."""
    native = tiny("vla_jepa")
    native.config.resize_images_to = (96, 96)
    native._vision_owner.deepstack_visual_indexes = []  # so the native control reproduces it exactly
    assert native.token_grid == (3, 3)
    raw = raw_images(native, 2, size=SIZE)
    seen = []
    qwen = native._qwen
    hook = qwen.language_model.register_forward_pre_hook(
        lambda m, args, kwargs: seen.append(kwargs["inputs_embeds"][kwargs["visual_pos_masks"]]), with_kwargs=True)
    noise, _ = fixed_noise_time(native, 2)
    chunk = native.predict(native.prepare(raw), noise)
    hook.remove()
    tokens = [native.native_tokens(raw[k]) for k in native.camera_keys]
    assert tokens[0].shape == (2, 9, 64)
    torch.testing.assert_close(seen[0].float(), torch.stack(tokens, dim=1).flatten(0, 2), atol=0.02, rtol=0.02)
    control = tiny("vla_jepa")
    control.config.resize_images_to = (96, 96)
    control.graft(PassThroughProjector(control.lm_width))
    cached = {**{k: v for k, v in raw.items() if not k.startswith("observation.images.")},
              **{feature_key(k): t for k, t in zip(native.camera_keys, tokens)}}
    torch.testing.assert_close(control.predict(control.prepare(cached), noise), chunk)
    assert control.config.resize_images_to == (96, 96)


def test_activation_checkpointing_keeps_the_projector_gradients_and_lowers_the_peak() -> None:
    """Qwen's decoder layers and the DiT blocks recompute during backward: the same gradients, less memory held
    by Qwen's forward and backward (measured as tensors alive at once, as tests/backbones/test_contract.py measures the
    other backbones; the tiny step's own peak is the processor's pass over the prompt's blank frames, before Qwen
    runs: 31.5 MB either way at this batch, so Qwen is measured on its own, from the grafted prompt)."""
    adapter = grafted("vla_jepa")
    adapter.policy.train()
    batch = adapter.prepare(raw_features(adapter, 8))
    noise, time = fixed_noise_time(adapter, 8)
    model = adapter.policy.model
    inputs = adapter.policy._prepare_model_inputs(batch)
    prompt = model.qwen.build_inputs(inputs["images"], inputs["instructions"], model.replace_prompt,
                                     model.embodied_replace_prompt)
    grads, peaks = {}, {}
    for on in (False, True, False):  # off again: the switch restores the plain step, KV cache included
        adapter.set_recompute(on)
        adapter.projector.zero_grad(set_to_none=True)
        adapter.loss(batch, noise=noise, time=time).mean().backward()
        grads[on] = [p.grad.clone() for p in adapter.projector.parameters()]
        peaks[on] = peak_tensor_bytes(lambda: model._qwen_last_decoder_hidden(prompt).float().sum().backward())
    assert adapter.spec.can_recompute and adapter._qwen.language_model.config.use_cache
    for plain, checkpointed in zip(grads[False], grads[True], strict=True):
        torch.testing.assert_close(checkpointed, plain, rtol=0, atol=1e-6)
    assert peaks[True] < 0.6 * peaks[False], peaks  # measured: 7.6 of 16.2 MB


def test_released_geometry_on_the_meta_device(tmp_path) -> None:
    """lerobot/VLA-JEPA-LIBERO at LIBERO's 256 px: Qwen3-VL-2B (ViT 1024 x 24 blocks, merger into the 2048-wide,
    28-layer LM, deepstack after blocks 5/11/17) + DiT-B x 16, ~2.28B parameters without the world model (counted
    from shapes, nothing allocated); 8x8 = 64 tokens per camera. The prompt's image pads come from the policy's own
    `build_inputs` at Qwen3-VL-2B's processor bounds."""
    from transformers import Qwen3VLConfig

    from graftcache.backbones.tiny_assets import QWEN3_VL_DIR, QWEN3_VL_PIXELS
    from graftcache.backbones.vla_jepa.tiny import (
        QWEN3_VL_2B,
        construct,
        vla_jepa_released_config,
    )

    config = vla_jepa_released_config(("image", "image2"), 256, 8, 7, "cpu")
    policy = lean_load.construct(lambda: construct(config, QWEN3_VL_DIR, Qwen3VLConfig(**QWEN3_VL_2B)), config)
    policy.model.qwen.model.tie_weights()
    adapter = VLAJEPAAdapter(policy, None, None, source="meta", random_init=True)
    qwen = adapter._qwen
    params = {name: sum(p.numel() for p in m.parameters()) for name, m in (
        ("vit", qwen.visual), ("merger", qwen.visual.merger), ("lm", qwen.language_model),
        ("head", policy.model.action_model), ("policy", policy))}
    layer = 2 * 2048 * 2048 + 2 * 2048 * 1024 + 2 * 128 + 3 * 2048 * 6144 + 2 * 2048  # q, o, k, v, qk-norms, MLP, norms
    assert params["lm"] == 151936 * 2048 + 28 * layer + 2048 == 1_720_574_976
    assert params["merger"] == 2 * 1024 + (4096 * 4096 + 4096) + (4096 * 2048 + 2048) == 25_174_016
    assert params["vit"] == 406_957_056 and params["head"] == 155_182_343
    assert params["policy"] == adapter.n_params == 2_282_714_375, params
    assert all(p.is_meta for p in policy.parameters())
    assert adapter.lm_width == 2048 and adapter.chunk_size == 7 and adapter.num_steps == 4
    assert qwen.visual.deepstack_visual_indexes == [5, 11, 17] and qwen.visual.merger.linear_fc2.out_features == 2048
    assert {p.dtype for p in qwen.parameters()} == {torch.bfloat16}
    assert config.qwen_model_name == "Qwen/Qwen3-VL-2B-Instruct" and not config.enable_world_model
    processor = policy.model.qwen.processor.image_processor
    processor.size = type(processor.size)(shortest_edge=QWEN3_VL_PIXELS[0], longest_edge=QWEN3_VL_PIXELS[1])
    hub_layout = {"patch_size": 16, "merge_size": 2, "temporal_patch_size": 2,  # Qwen3-VL-2B's preprocessor_config
                  "size": {"shortest_edge": QWEN3_VL_PIXELS[0], "longest_edge": QWEN3_VL_PIXELS[1]}}
    (tmp_path / "preprocessor_config.json").write_text(json.dumps(hub_layout))
    config.qwen_model_name = str(tmp_path)
    assert VLAJEPAAdapter._grid_of_config(config, None) == (8, 8)
    images = [[torch.rand(3, 256, 256) for _ in adapter.camera_keys] for _ in range(2)]
    model = policy.model
    cpu = mock.PropertyMock(return_value=torch.device("cpu"))  # the prompt's tensors follow the (meta) model
    with mock.patch.object(type(model.qwen.model), "device", new_callable=lambda: cpu):
        inputs = model.qwen.build_inputs(images, ["open the drawer", "put the bowl"], model.replace_prompt,
                                         model.embodied_replace_prompt)
    assert inputs["image_grid_thw"].tolist() == [[1, 16, 16]] * 4  # 256 px: 16x16 patches -> 2x2 merge -> 8x8
    pads = inputs["mm_token_type_ids"] == 1  # the tiny tokenizer's own image-pad id marks the slots
    assert pads.sum(dim=1).tolist() == [2 * 64, 2 * 64]
    embodied = inputs["input_ids"] == model.embodied_action_token_id
    actions = torch.isin(inputs["input_ids"], model._action_token_ids_t)
    assert embodied.sum(dim=1).tolist() == [32, 32] and actions.sum(dim=1).tolist() == [24, 24]
