"""Wall-X as a backbone: tiny geometry (built offline from the shipped tiny MoE config and EO-1's tiny Qwen
processor), the native tower against the policy's own image path, the loss and the sampler against lerobot's
`forward` / `predict_action_chunk` under the same random draws (flow loss only: no token labels in flow mode), the
graft slots (the image-pad positions), and the released geometry on the meta device (4.2B
parameters are never materialised). The native control, LoRA and reset, save/load by hub id and the missing base:
tests/backbones/test_zoo_common.py."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from helpers.backbones import (
    ENC_DIM,
    assert_projector_trained,
    assert_refuses_odd_token_counts,
    assert_tiny_zoo_geometry,
    fixed_noise_time,
    grafted,
    lm_inputs_of_loss,
    pooled_raw,
    raw_features,
    raw_images,
    tiny,
)

from graftcache.backbones.given_draws import given_noise
from graftcache.backbones.wall_x.adapter import WallXAdapter
from graftcache.errors import BackboneError
from graftcache.graft import FusedProjector, GraftProjector, feature_key

SIZE = 128  # the tiny policy's frames: Wall-X resizes to 256 -> 252 px, the tiny processor to 112 px -> 4x4 tokens


def _image_pads(adapter, batch) -> torch.Tensor:
    return batch["input_ids"] == adapter.policy.model.config.image_token_id


def test_tiny_geometry() -> None:
    adapter = tiny("wall_x")
    assert adapter.num_steps == 10  # `predict`'s default: lerobot's policy passes no other
    merger = 32 + (128 * 128 + 128) + (128 * 64 + 64)  # RMSNorm(32), Linear(4 x 32 -> 128), Linear(128 -> 64)
    assert_tiny_zoo_geometry(adapter, 20, merger, 250_784)
    experts = 2 * 3 * 64 * (128 + 64)  # two layers, each with Wall-X's VLM expert (64 -> 128) and action expert
    assert sum(p.numel() for n, p in adapter.policy.model.model.named_parameters() if ".moe." in n) == experts
    tokenizer = adapter.policy.model.processor.tokenizer  # merge_tokenizer.py's two tokens, left padding
    assert tokenizer.padding_side == "left" and len(tokenizer) == adapter.policy.model.config.vocab_size
    assert {"<|propri|>", "<|action|>"} <= set(tokenizer.get_vocab())


def test_native_tower_is_the_policys_own_image_path() -> None:
    """Native tokens equal what Wall-X's ViT embeds for each camera from the policy's own `preprocess_inputs`, and
    the patch grid is in raster order: regrouped into 2x2 blocks, the merger maps it onto those tokens."""
    adapter = tiny("wall_x")
    raw = raw_images(adapter, 3, size=SIZE)
    inputs = adapter.policy.preprocess_inputs(adapter.prepare(raw))
    assert _image_pads(adapter, inputs).sum(dim=1).tolist() == [2 * 16] * 3
    visual = adapter.policy.model.visual
    with torch.no_grad():
        own = visual(inputs["pixel_values"].to(visual.dtype), grid_thw=inputs["image_grid_thw"]).pooler_output
    own = own.float().view(3, 2, 16, 64)  # images in the prompt: sample after sample, camera after camera
    for i, key in enumerate(adapter.camera_keys):
        torch.testing.assert_close(adapter.native_tokens(raw[key]), own[:, i])
    grid = adapter.native_patch_grid(raw[adapter.camera_keys[0]])
    blocks = grid.view(3, 4, 2, 4, 2, 32).permute(0, 1, 3, 2, 4, 5).reshape(-1, 32)
    with torch.no_grad():
        merged = visual.merger(blocks.to(visual.dtype)).float()
    torch.testing.assert_close(merged.view(3, 16, 64), own[:, 0])


def test_loss_and_prediction_are_lerobots_under_the_same_draws() -> None:
    """Wall-X's loss is its flow MSE alone (no labels in flow mode, so no cross-entropy term): lerobot's scalar is
    the mean of the per-element losses over its 20 padded dims with the padded ones zeroed (its dof mask)."""
    from lerobot.policies.wall_x import modeling_wall_x

    adapter = tiny("wall_x")
    adapter.policy.eval()
    batch = adapter.prepare(raw_images(adapter, 3, size=SIZE))
    head = adapter.policy.model.action_preprocessor
    with torch.no_grad():
        torch.manual_seed(7)
        reference, parts = adapter.policy.forward(dict(batch))
        torch.manual_seed(7)  # modeling_wall_x.py draws Wall-X's time, then the noise
        time = 1 - head.sample_time(3, "cpu")
        noise = torch.randn(3, adapter.chunk_size, adapter.max_action_dim)
        losses = adapter._flow_losses(batch, noise, time)
        assert set(parts) == {"loss", "flow_loss"}
        dof = (torch.arange(adapter.max_action_dim) < adapter.action_dim).float()
        torch.testing.assert_close((losses * dof).mean(), reference)
        inference = {k: v for k, v in batch.items() if k not in ("action", "action_is_pad")}
        torch.manual_seed(11)
        chunk_ref = adapter.policy.predict_action_chunk(dict(inference))
        torch.manual_seed(11)
        start = torch.randn(3, adapter.chunk_size, adapter.max_action_dim)
    torch.testing.assert_close(adapter.predict(batch, start), chunk_ref)
    assert chunk_ref.shape == (3, adapter.chunk_size, adapter.action_dim)
    few = adapter.predict(batch, start, num_steps=2)
    assert few.shape == chunk_ref.shape and not torch.allclose(few, chunk_ref)  # the step count reaches the ODE
    with pytest.raises(BackboneError, match=r"wall_x: noise of shape \(3, 10, 7\) given, \(3, 10, 20\) drawn by "
                                            r"torch.randn_like in lerobot.policies.wall_x.modeling_wall_x"):
        adapter._flow_losses(batch, noise[:, :, :7], time)
    with given_noise(modeling_wall_x, noise, "wall_x", draws=("randn",)), \
            pytest.raises(BackboneError, match=r"given, \(2, 2\) drawn by torch.randn in"):
        modeling_wall_x.torch.randn(2, 2)


def test_graft_fills_the_image_pads_with_projected_features() -> None:
    adapter = grafted("wall_x")
    assert {n for n, p in adapter.policy.named_parameters() if p.requires_grad} == {
        f"model.visual.merger.{p}" for p in ("norm.weight", "norm.bias", "proj.weight", "proj.bias")}
    raw = raw_features(adapter, 2)
    batch = adapter.prepare(raw)
    noise, time = fixed_noise_time(adapter, 2)
    seen, loss = lm_inputs_of_loss(adapter, adapter.policy.model.model, batch, noise, time)
    inputs = adapter.policy.preprocess_inputs(batch)
    cameras = [raw[feature_key(k)] for k in adapter.camera_keys]
    expected = adapter.projector(torch.stack(cameras, dim=1).flatten(0, 2).bfloat16())  # Wall-X's cast to the ViT's
    torch.testing.assert_close(seen["inputs_embeds"][_image_pads(adapter, inputs)], expected.bfloat16())
    assert_projector_trained(adapter, loss)
    assert_refuses_odd_token_counts(adapter, raw, noise, time)


def test_fused_projectors_each_fill_their_own_samples_image_pads() -> None:
    """A backbone pass of two cells (graftcache.graft.FusedProjector): each member projects its own sample's
    cameras into that sample's image pads."""
    adapter = tiny("wall_x")
    members = [GraftProjector(ENC_DIM, adapter.lm_width) for _ in range(2)]
    adapter.graft(FusedProjector(members))
    raw = raw_features(adapter, 2)
    batch = adapter.prepare(raw)
    seen = {}
    hook = adapter.policy.model.model.register_forward_pre_hook(lambda m, a, kw: seen.update(kw), with_kwargs=True)
    with adapter.projector.rows([1, 1]), torch.no_grad():
        adapter.loss(batch, *fixed_noise_time(adapter, 2))
    hook.remove()
    pads = _image_pads(adapter, adapter.policy.preprocess_inputs(batch))
    for i, member in enumerate(members):
        cameras = torch.cat([raw[feature_key(k)][i] for k in adapter.camera_keys]).bfloat16()
        with torch.no_grad():
            torch.testing.assert_close(seen["inputs_embeds"][i][pads[i]], member(cameras).bfloat16())


def test_pooled_features_get_a_prompt_with_their_grid() -> None:
    """The pool-HxW controls: a 2x2 pooled grid gets 4 image pads per camera and the grid_thw of a 2x2 merged image
    (the processor's bounds pinned to 56x56 px for the call), so the projected tokens fill exactly those slots."""
    adapter = grafted("wall_x")
    bounds = dict(adapter._image_processor.size)
    batch = adapter.prepare(pooled_raw(adapter))
    inputs = adapter.policy.preprocess_inputs(batch)
    assert _image_pads(adapter, inputs).sum(dim=1).tolist() == [8, 8]
    assert inputs["image_grid_thw"].tolist() == [[1, 4, 4]] * 4 and inputs["pixel_values"].shape == (16, ENC_DIM)
    noise, time = fixed_noise_time(adapter, 2)
    assert torch.isfinite(adapter.loss(batch, noise, time)).all()
    assert dict(adapter._image_processor.size) == bounds  # the bounds are the policy's again


def test_activation_checkpointing_keeps_the_gradients() -> None:
    adapter = grafted("wall_x")
    batch = adapter.prepare(raw_features(adapter, 2))
    noise, time = fixed_noise_time(adapter, 2)
    grads = []
    for on in (False, True):
        adapter.set_recompute(on)
        adapter.projector.zero_grad()
        adapter.loss(batch, noise, time).mean().backward()
        grads.append([p.grad.clone() for p in adapter.projector.parameters()])
    for plain, recomputed in zip(*grads):
        torch.testing.assert_close(plain, recomputed)


def _released_base(folder: Path) -> Path:
    """A stand-in for x-square-robot/wall-oss-flow's snapshot: its config, and a processor with Qwen2.5-VL's own
    image processor (its pixel bounds) around the tiny tokenizer."""
    from lerobot.policies.wall_x.qwen_model import Qwen2_5_VLConfig
    from transformers import Qwen2_5_VLProcessor
    from transformers.models.qwen2_vl import Qwen2VLImageProcessor

    from graftcache.backbones.wall_x.tiny import WALL_OSS_FLOW, tiny_processor

    Qwen2_5_VLConfig(**WALL_OSS_FLOW).save_pretrained(folder)
    tiny = tiny_processor()
    Qwen2_5_VLProcessor(image_processor=Qwen2VLImageProcessor(), tokenizer=tiny.tokenizer,
                        video_processor=tiny.video_processor, chat_template=tiny.chat_template).save_pretrained(folder)
    return folder


def test_released_geometry_on_the_meta_device(tmp_path) -> None:
    """lerobot's Wall-X (x-square-robot/wall-oss-flow) at LIBERO's 256 px: Qwen2.5-VL-3B's ViT (1280 x 32 blocks,
    merger into the 2048-wide, 36-layer LM) plus the 2048 -> 2048 action expert in every layer, 9x9 = 81 tokens per
    camera, ~4.2B parameters with the vocabulary from_pretrained resizes to (counted from shapes, nothing
    allocated). The prompt's image pads come from the policy's own `preprocess_inputs`."""
    from graftcache.backbones.lean_load import construct as lean_construct
    from graftcache.backbones.wall_x.tiny import WALL_OSS_VOCAB, construct, wallx_released_config

    base = _released_base(tmp_path / "wall-oss-flow")
    config = wallx_released_config(("image", "image2"), 256, 8, 7, "cpu")
    policy = lean_construct(lambda: construct(config, base), config)
    model = policy.model
    model.resize_token_embeddings(WALL_OSS_VOCAB, mean_resizing=False)  # the released tokenizer's length
    model.tie_weights()
    adapter = WallXAdapter(policy, None, None, source="meta", random_init=True)
    params = {name: sum(p.numel() for p in m.parameters()) for name, m in (
        ("vit", model.visual), ("merger", model.visual.merger), ("lm", model.model),
        ("experts", model.model.layers[0].moe.experts[1]), ("head", model.action_preprocessor), ("wall_x", policy))}
    assert params["vit"] == 668_684_288 and params["merger"] == 36_708_608  # EO-1's Qwen2.5-VL-3B ViT
    assert params["experts"] == 3 * 2048 * 2048 and params["head"] == 2 * 40 * 2048 + 3 * 2048 * 2048 + 2048 * 20
    assert params["lm"] == 3_085_938_688 - 151_936 * 2048 + WALL_OSS_VOCAB * 2048 + 36 * 3 * 2048 * 2048, params
    assert params["wall_x"] == adapter.n_params == 4_224_038_912, params
    assert model.lm_head.weight is model.model.embed_tokens.weight
    assert adapter.token_grid == (9, 9) and adapter.lm_width == 2048
    assert adapter.max_action_dim == 20 and adapter.chunk_size == 32 and adapter.num_steps == 10
    assert {p.dtype for p in model.model.layers.parameters() if p.ndim == 2} == {torch.bfloat16}
    assert {p.dtype for p in model.action_preprocessor.parameters()} == {torch.float32}  # lerobot keeps it fp32
    raw = {k: torch.rand(2, 3, 256, 256) for k in adapter.camera_keys}
    batch = {**raw, "observation.state": torch.zeros(2, 8), "task": ["open the drawer.", "put the bowl."]}
    inputs = policy.preprocess_inputs(batch)
    assert inputs["image_grid_thw"].tolist() == [[1, 18, 18]] * 4  # 252 px: 18x18 patches -> 2x2 merge -> 9x9
    pad = model.processor.tokenizer.convert_tokens_to_ids("<|image_pad|>")  # the stand-in tokenizer's own id
    assert (inputs["input_ids"] == pad).sum(dim=1).tolist() == [2 * 81, 2 * 81]
    assert inputs["moe_token_types"].sum(dim=1).tolist() == [32, 32]  # the action expert's tokens: the chunk
