"""The adapters of the policies whose images lerobot prepares itself and embeds with its VLM's `embed_image`
(spec `image_method` `prepare_images` or `_preprocess_images`: SmolVLA and the PaliGemma policies): geometry, batches,
graft surgery, policy loss, native tower. What every backbone does alike is tests/backbones/test_contract.py.

Flow tests run on those with a flow time (FLOW); a token loss's own tests are its backbone's file."""

from __future__ import annotations

import math

import pytest
import torch
from helpers.backbones import (
    ENC_DIM,
    TASKS,
    TINY,
    assert_native_control_reproduces,
    backbones_where,
    fixed_noise_time,
    grafted,
    raw_features,
    raw_images,
    tiny,
)

from graftcache.backbones import BACKBONES, get_backbone
from graftcache.errors import BackboneError
from graftcache.graft import GraftProjector, feature_key

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # tests/fixtures/torch_threads.py

#: lerobot's own image preparation, embedded by the VLM's `embed_image`
EMBEDDING = ("prepare_images", "_preprocess_images")
NAMES = backbones_where(lambda spec: spec.image_method in EMBEDDING)
FLOW = backbones_where(lambda spec: spec.image_method in EMBEDDING and spec.flow_time is not None)


def test_registry_maps_names_to_adapters() -> None:
    assert NAMES and [get_backbone(n).name for n in BACKBONES] == list(BACKBONES)
    with pytest.raises(BackboneError, match="unknown backbone 'octo'"):
        get_backbone("octo")


@pytest.mark.parametrize("name", NAMES)
def test_tiny_geometry(name: str) -> None:
    adapter = tiny(name)
    assert adapter.token_grid == (4, 4)
    assert adapter.lm_width == adapter._vision_owner.config.text_config.hidden_size
    assert adapter.embed_scale == pytest.approx(math.sqrt(adapter.lm_width) if adapter.spec.scaled_embeddings else 1.0)
    assert adapter.cameras == ("image", "image2")
    assert adapter.camera_keys == ("observation.images.image", "observation.images.image2")
    assert (adapter.state_dim, adapter.action_dim, adapter.chunk_size) == (8, 7, TINY.chunk_size)
    # pi0-FAST decodes up to a whole chunk of FAST tokens (<bos> "Action: " ... "|" <eos>), no denoising steps
    steps = TINY.chunk_size * 7 + 6 if adapter.spec.flow_time is None else TINY.num_steps
    assert adapter.num_steps == steps and adapter.random_init and adapter.source == "tiny"
    report = adapter.freeze_report()
    assert report.total == sum(p.numel() for p in adapter.policy.parameters())


@pytest.mark.parametrize("name", NAMES)
def test_native_tower_outputs_match_what_the_policy_embeds(name: str) -> None:
    adapter = tiny(name)
    images = torch.rand(3, 3, 96, 128)  # non-square: the policy pads and resizes
    grid, tokens = adapter.native_patch_grid(images), adapter.native_tokens(images)
    assert grid.shape[0] == 3 and grid.shape[1] * grid.shape[2] >= 16
    assert tokens.shape == (3, 16, adapter.lm_width)
    prepared, _ = getattr(adapter.policy, adapter.image_method)({adapter.camera_keys[0]: images})
    with torch.no_grad():
        model = adapter.policy.model
        vlm = model.vlm_with_expert if hasattr(model, "vlm_with_expert") else model.paligemma_with_expert
        embedded = vlm.embed_image(prepared[0])
    torch.testing.assert_close(tokens, embedded.float())


@pytest.mark.parametrize("name", [n for n in NAMES if not get_backbone(n).spec.prompt_uses_state])
def test_prompt_without_state_is_tokenised_once_per_task_and_matches_lerobot(name: str) -> None:
    adapter = grafted(name)
    raw = raw_features(adapter, 6)
    ours, lerobot = adapter.prepare(raw), adapter.preprocessor(dict(raw))
    assert torch.equal(ours["observation.language.tokens"], lerobot["observation.language.tokens"])
    assert torch.equal(ours["observation.language.attention_mask"], lerobot["observation.language.attention_mask"])
    for key in ("observation.state", "action", feature_key("image"), feature_key("image2")):
        torch.testing.assert_close(ours[key], lerobot[key])
    assert ours[feature_key("image")].shape == (6, 16, ENC_DIM)  # features are not unsqueezed
    assert not torch.allclose(ours["observation.state"], raw["observation.state"])  # normalised

    tokenizer_step = adapter._token_steps[-1]
    calls = []
    real = tokenizer_step.input_tokenizer

    class Counting:
        def __call__(self, *args, **kwargs):
            calls.append(args[0])
            return real(*args, **kwargs)

        def __getattr__(self, attr):
            return getattr(real, attr)

    tokenizer_step.input_tokenizer = Counting()
    adapter._task_cache.clear()
    adapter.prepare(raw_features(adapter, 8))
    adapter.prepare(raw_features(adapter, 5, seed=3))
    assert len(calls) == len(TASKS)
    ids, mask = adapter.task_tokens([TASKS[1], TASKS[0]])
    assert ids.shape == mask.shape and ids.shape[0] == 2 and mask[0].sum() < mask[1].sum()


@pytest.mark.parametrize("name", [n for n in NAMES if get_backbone(n).spec.prompt_uses_state])
def test_prompt_holding_the_state_is_tokenised_per_batch(name: str) -> None:
    adapter = grafted(name)
    with pytest.raises(BackboneError, match="discretised state"):
        adapter.task_tokens(list(TASKS))
    raw = raw_features(adapter, 4)
    batch = adapter.prepare(raw)
    raw["observation.state"] = raw["observation.state"] + 1.0
    assert not torch.equal(batch["observation.language.tokens"], adapter.prepare(raw)["observation.language.tokens"])


@pytest.mark.parametrize("name", NAMES)
def test_graft_trains_only_the_projector(name: str) -> None:
    adapter = grafted(name)
    batch = adapter.prepare(raw_features(adapter, 8))
    noise, time = fixed_noise_time(adapter, 8)
    trainable = [n for n, p in adapter.policy.named_parameters() if p.requires_grad]
    assert trainable and all(".norm." in n or ".proj." in n for n in trainable)
    assert adapter.freeze_report().trainable == sum(p.numel() for p in adapter.projector.parameters())
    before = {k: v.clone() for k, v in adapter.policy.state_dict().items()}
    optimiser = torch.optim.AdamW([p for p in adapter.policy.parameters() if p.requires_grad], lr=1e-2)
    adapter.policy.train()
    for _ in range(3):
        loss = adapter.loss(batch, noise, time).mean()
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
    after = adapter.policy.state_dict()
    assert before.keys() == after.keys()
    changed = {k for k in before if not torch.equal(before[k], after[k])}
    projector_keys = {k for k in before if any(k.endswith(f"{n}") for n in trainable)}
    assert changed == projector_keys == set(trainable)


@pytest.mark.parametrize("name", [n for n in NAMES if not get_backbone(n).spec.scaled_embeddings])
def test_gradients_reach_the_projector_on_tiny_paligemma_backbones(name: str) -> None:
    adapter = grafted(name)
    batch = adapter.prepare(raw_features(adapter, 4))
    adapter.loss(batch, *fixed_noise_time(adapter, 4)).mean().backward()
    assert adapter.projector.proj.weight.grad.abs().sum() > 0
    assert adapter.projector.norm.weight.grad.abs().sum() > 0
    assert all(p.grad is None for p in adapter.policy.parameters() if not p.requires_grad)


@pytest.mark.parametrize("name", FLOW)
def test_predict_is_deterministic_for_fixed_noise(name: str) -> None:
    adapter = grafted(name)
    batch = adapter.prepare(raw_features(adapter, 4))
    noise, _ = fixed_noise_time(adapter, 4)
    adapter.policy.train()
    first = adapter.predict(batch, noise)
    assert first.shape == (4, adapter.chunk_size, adapter.action_dim)
    assert torch.equal(first, adapter.predict(batch, noise.clone()))
    assert not torch.allclose(first, adapter.predict(batch, noise + 0.5))
    assert not torch.allclose(first, adapter.predict(batch, noise, num_steps=1))
    assert adapter.policy.training  # predict restores the training mode
    assert adapter.unnormalize(first).shape == first.shape


@pytest.mark.parametrize("name", FLOW)
def test_loss_is_the_masked_mean_over_real_steps_and_dims(name: str) -> None:
    adapter = grafted(name)
    batch = adapter.prepare(raw_features(adapter, 4))
    noise, time = fixed_noise_time(adapter, 4)
    with torch.no_grad():
        elements = adapter._flow_losses(batch, noise, time)[:, :, : adapter.action_dim]
        loss = adapter.loss(batch, noise, time)
        unpadded = adapter.loss({**batch, "action_is_pad": torch.zeros_like(batch["action_is_pad"])}, noise, time)
    assert elements.shape == (4, adapter.chunk_size, 7) and loss.shape == (4,)
    torch.testing.assert_close(loss[0], elements[0, :-3].mean())  # sample 0: last 3 steps padded
    torch.testing.assert_close(loss[1:], elements[1:].mean(dim=(1, 2)))
    torch.testing.assert_close(unpadded[1:], loss[1:])
    assert unpadded[0] != loss[0]


@pytest.mark.parametrize("name", NAMES)
def test_native_control_reproduces_the_ungrafted_policy(name: str) -> None:
    """Cached post-connector tokens through the pass-through projector = the policy on pixels."""
    assert_native_control_reproduces(tiny(name), tiny(name), 4)


@pytest.mark.parametrize("name", NAMES)
def test_full_policy_trains_on_pixels(name: str) -> None:
    """What train-tiny needs of the tiny backbones: the real tower, all parameters, raw images."""
    adapter = tiny(name)
    for p in adapter.policy.parameters():
        p.requires_grad_(True)
    adapter.policy.train()
    batch = adapter.prepare(raw_images(adapter, 4))
    adapter.loss(batch).mean().backward()
    tower, connector = adapter._tower_and_connector()
    assert all(p.grad is not None for p in connector.parameters())
    assert sum(p.grad.abs().sum() for p in tower.parameters() if p.grad is not None) > 0


def test_graft_and_batch_errors_name_the_problem() -> None:
    adapter = tiny("smolvla")
    with pytest.raises(BackboneError, match="width 64, the LM expects 192"):
        adapter.graft(GraftProjector(ENC_DIM, 64))
    with pytest.raises(BackboneError, match="observation.images.image2"):
        adapter.prepare({k: v for k, v in raw_images(adapter, 2).items() if k != "observation.images.image2"})
    adapter.graft(GraftProjector(ENC_DIM, adapter.lm_width))
    with pytest.raises(BackboneError, match="already grafted"):
        adapter.graft(GraftProjector(ENC_DIM, adapter.lm_width))
    with pytest.raises(BackboneError, match="removed by graft"):
        adapter.native_tokens(torch.rand(1, 3, 32, 32))
    with pytest.raises(BackboneError, match="observation.vis_feats.image2"):
        adapter.prepare({k: v for k, v in raw_features(adapter, 2).items() if k != feature_key("image2")})
    with pytest.raises(BackboneError, match=r"observation.vis_feats.image: expected \[B, T, 48\]"):
        adapter.loss(adapter.prepare(raw_features(adapter, 2, enc_dim=32)))
