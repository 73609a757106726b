"""pi0 and pi0-FAST as backbones: pi0-FAST's own objective (lerobot's cross-entropy on FAST tokens, greedy
decoding for scoring) and its FAST tokenizer, and both policies' released geometry on the meta device (3-4B
parameters are never materialised here: shapes only, counted against the architectures' own formulas)."""

from __future__ import annotations

import itertools
import json

import numpy as np
import pytest
import torch
from helpers.backbones import ENC_DIM, checkpointing_peaks, fixed_noise_time, grafted, raw_features, raw_images, tiny
from scipy.fft import dct, idct

from graftcache.backbones import load_backbone
from graftcache.backbones.objectives import FlowObjective
from graftcache.backbones.pi0_fast.fast import FAST_DIR
from graftcache.errors import BackboneError
from graftcache.graft import GraftProjector, feature_key

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # tests/fixtures/torch_threads.py


# ---------------------------------------------------------------------------------------------- pi0-FAST
def test_fast_tokens_of_a_chunk_are_its_quantised_dct_and_decode_back() -> None:
    """The training targets are FAST tokens of the normalised chunk; lerobot's decoder (what scoring uses)
    turns them back into exactly the inverse DCT of the quantised coefficients, computed here with scipy."""
    adapter = tiny("pi0_fast")
    raw = raw_images(adapter, 3)
    raw["action"] = raw["action"].clamp(-1.6, 1.6)  # inside the stats' range: every coefficient in the alphabet
    batch = adapter.prepare(raw)
    tokens, mask = batch["action.tokens"], batch["action.token_mask"]
    assert tokens.shape == mask.shape == (3, adapter.config.max_action_tokens) and not mask[:, -1].any()
    fast = adapter.policy.action_tokenizer
    normalised = ((raw["action"] - 0.1) / 0.8).numpy().astype(np.float64)  # helpers' stats: mean 0.1, std 0.8
    quantised = np.around(dct(normalised, axis=1, norm="ortho") * fast.scale)
    expected = idct(quantised / fast.scale, axis=1, norm="ortho")
    decoded = adapter.policy.detokenize_actions(tokens[:, 1:], action_horizon=adapter.chunk_size,
                                                action_dim=adapter.action_dim)  # generation starts after <bos>
    np.testing.assert_allclose(decoded.numpy(), expected, atol=1e-5)
    assert np.abs(expected - normalised).max() < 0.05 * np.sqrt(2 * adapter.chunk_size)  # quantisation only


def test_fast_loss_is_lerobots_cross_entropy_and_trains_the_projector() -> None:
    adapter = grafted("pi0_fast")
    batch = adapter.prepare(raw_features(adapter, 4))
    adapter.policy.train()
    loss = adapter.loss(batch, *fixed_noise_time(adapter, 4))  # flow inputs are ignored
    reference, parts = adapter.policy.forward(dict(batch))  # lerobot's own training forward
    assert loss.shape == () and torch.equal(loss, reference) and parts["ce_loss"] == pytest.approx(loss.item())
    optimiser = torch.optim.Adam(adapter.projector.parameters(), lr=5e-2)
    losses = []
    for _ in range(8):
        value = adapter.loss(batch)
        optimiser.zero_grad()
        value.backward()
        optimiser.step()
        losses.append(value.item())
    # image tokens move a random tiny LM's FAST-token predictions only a little: steadily, though
    assert all(b < a for a, b in itertools.pairwise(losses)) and losses[-1] < 0.98 * losses[0], losses
    assert not isinstance(adapter, FlowObjective) and not hasattr(adapter, "_flow_losses")  # a token objective only


def test_fast_predict_decodes_greedily_whatever_the_noise() -> None:
    adapter = grafted("pi0_fast")
    batch = adapter.prepare(raw_features(adapter, 3))
    noise, _ = fixed_noise_time(adapter, 3)
    config = adapter.config
    saved = (config.temperature, config.n_action_steps, config.validate_action_token_prefix)
    adapter.policy.train()
    first = adapter.predict(batch, noise)
    assert first.shape == (3, adapter.chunk_size, adapter.action_dim) and torch.isfinite(first).all()
    assert torch.equal(first, adapter.predict(batch, noise + 1.0, num_steps=1))  # no noise, no denoising steps
    assert adapter.policy.training  # predict restores the training mode ...
    assert (config.temperature, config.n_action_steps, config.validate_action_token_prefix) == saved  # ... and config
    other = adapter.prepare(raw_features(adapter, 3, seed=5))
    assert not torch.equal(first, adapter.predict(other, noise))  # the features reach the decoded chunk


def test_fast_checkpoint_carries_its_tokenizer_and_refuses_one_it_cannot_find(tmp_path) -> None:
    original = tiny("pi0_fast", seed=1)
    folder = original.save(tmp_path / "ckpt")
    assert {"tokenizer.json", "processor_config.json"} <= {p.name for p in (folder / FAST_DIR).iterdir()}
    loaded = load_backbone("pi0_fast", folder)
    assert loaded.policy_sha256 == original.policy_sha256
    raw = raw_images(original, 2)
    for key in ("action.tokens", "observation.language.tokens"):
        assert torch.equal(loaded.prepare(dict(raw))[key], original.prepare(dict(raw))[key])
    for entry in (folder / FAST_DIR).iterdir():
        entry.unlink()
    (folder / FAST_DIR).rmdir()
    config = json.loads((folder / "config.json").read_text())
    config["action_tokenizer_name"] = "lerobot/fast-action-tokenizer"  # lerobot's default: a hub repo
    (folder / "config.json").write_text(json.dumps(config))
    with pytest.raises(BackboneError, match=r"FAST action tokenizer 'lerobot/fast-action-tokenizer' is neither a "
                                            r"local folder nor in the Hugging Face cache"):
        load_backbone("pi0_fast", folder)


# ---------------------------------------------------------------------------------------------- released geometry
def _siglip(width: int, mlp: int, depth: int, patch: int, image: int) -> int:
    """Parameters of a SigLIP vision tower (patch conv, position table, pre-norm blocks, post norm)."""
    block = 4 * (width * width + width) + (width * mlp + mlp) + (mlp * width + width) + 2 * 2 * width
    return depth * block + (3 * patch * patch * width + width) + (image // patch) ** 2 * width + 2 * width


def _gemma(width: int, depth: int, mlp: int, heads: int, kv: int, head: int, vocab: int | None) -> int:
    """Parameters of a Gemma decoder (bias-free attention and gated MLP, RMS norms, optional token table)."""
    block = width * heads * head * 2 + width * kv * head * 2 + 3 * width * mlp + 2 * width
    return depth * block + width + (vocab * width if vocab else 0)


VOCAB = 257152  # PaliGemma's, hard-coded by lerobot (modeling_pi0.py:216)
TOWER = _siglip(1152, 4304, 27, 14, 224)  # So400m/14 at 224 px
CONNECTOR = 1152 * 2048 + 2048
GEMMA_2B = _gemma(2048, 18, 16384, 8, 1, 256, VOCAB)
EXPERT = _gemma(1024, 18, 4096, 8, 1, 256, None) + VOCAB * 1024  # gemma_300m: no token table, its own lm_head


def _released(name: str):
    """lerobot's own constructor at the released geometry (LIBERO's cameras and dims, chunk 50, pi0 with the
    LIBERO recipe's masked third slot), on the meta device, wrapped in the adapter."""
    from devtools.released import LIBERO, _construct_on_meta, _features, unit_stats
    from graftcache.backbones import get_backbone
    from graftcache.backbones.pi0_fast.fast import policy_tokenizers
    from graftcache.backbones.pi0_fast.tiny import fit_tiny_fast
    from graftcache.backbones.tiny import TinySpec
    from graftcache.backbones.tiny_assets import PALIGEMMA_DIR

    inputs, outputs = _features(LIBERO)
    if name == "pi0":
        from lerobot.policies.pi0.configuration_pi0 import PI0Config
        from lerobot.policies.pi0.modeling_pi0 import PI0Policy

        config = PI0Config(dtype="bfloat16", empty_cameras=1, device="cpu", input_features=inputs,
                           output_features=outputs)
        policy = _construct_on_meta(PI0Policy, config, torch.bfloat16)
    else:
        from lerobot.policies.pi0_fast.configuration_pi0_fast import PI0FastConfig
        from lerobot.policies.pi0_fast.modeling_pi0_fast import PI0FastPolicy

        config = PI0FastConfig(dtype="bfloat16", device="cpu", input_features=inputs, output_features=outputs)
        # construction reads none of the tokenizer's fit
        fast = fit_tiny_fast(unit_stats(LIBERO), TinySpec(chunk_size=config.chunk_size))
        with policy_tokenizers(fast, PALIGEMMA_DIR):
            policy = _construct_on_meta(PI0FastPolicy, config, torch.bfloat16)
    adapter = get_backbone(name)(policy, None, None, source="meta", random_init=True)
    adapter._sha256, adapter._pristine = "meta", {}  # graft() pins a hash and keeps a copy: nothing to read on meta
    return adapter


@pytest.mark.parametrize(("name", "slots", "others"), [
    ("pi0", ("image", "image2", "empty_camera_0"), {
        "action expert": EXPERT, "state projection": 32 * 1024 + 1024,  # max_state_dim 32 -> expert width
        # action_in_proj, action_out_proj (max_action_dim 32 <-> 1024), action_time_mlp_in (2048 -> 1024), _out
        "action/time projections": (32 * 1024 + 1024) + (1024 * 32 + 32) + (2048 * 1024 + 1024)
        + (1024 * 1024 + 1024)}),
    ("pi0_fast", ("image", "image2"), {}),
])
def test_released_geometry_on_the_meta_device(name: str, slots: tuple[str, ...], others: dict) -> None:
    adapter = _released(name)
    policy = adapter.policy
    groups = {k: sum(p.numel() for m in (v if isinstance(v, tuple) else (v,)) for p in m.parameters())
              for k, v in adapter._module_groups().items()}
    lm_head = VOCAB * 2048  # PaliGemma's own lm_head (pi0-FAST decodes with it; pi0 never uses it)
    expected = {"vision tower": TOWER, "connector": CONNECTOR, "language model": GEMMA_2B, **others}
    if name == "pi0_fast":
        expected["LM head"] = lm_head
    assert {k: groups[k] for k in expected} == expected
    total = sum(p.numel() for p in policy.parameters())
    assert total == sum(expected.values()) + (lm_head if name == "pi0" else 0)
    assert total == {"pi0": 4_028_019_472, "pi0_fast": 3_449_982_704}[name]

    assert adapter.token_grid == (16, 16) and adapter.lm_width == 2048 and adapter.embed_scale == 1.0
    assert tuple(k.removeprefix("observation.images.") for k in adapter.config.image_features) == slots
    assert adapter.cameras == ("image", "image2")
    tower, connector = adapter._tower_and_connector()
    hidden = tower(torch.empty(2, 3, 224, 224, device="meta")).last_hidden_state
    assert tuple(hidden.shape) == (2, 256, 1152) and tuple(connector(hidden).shape) == (2, 256, 2048)

    adapter.graft(GraftProjector(ENC_DIM, adapter.lm_width))
    features = {feature_key(c): torch.zeros(2, 256, ENC_DIM) for c in adapter.cameras}
    images, masks = getattr(policy, adapter.image_method)(features)  # the grafted slots, real values on the CPU
    assert [tuple(i.shape) for i in images] == [(2, 256, ENC_DIM)] * len(slots)
    assert [m.tolist() for m in masks] == [[True, True], [True, True], [False, False]][:len(slots)]
    meta = [i.to("meta") for i in images]
    tokens, token_mask = torch.zeros(2, 12, dtype=torch.long, device="meta"), torch.ones(2, 12, dtype=torch.bool,
                                                                                         device="meta")
    embed = policy.model.embed_prefix if name == "pi0" else policy.model.embed_prefix_fast
    embs = embed(meta, [m.to("meta") for m in masks], tokens, token_mask)[0]
    assert tuple(embs.shape) == (2, 256 * len(slots) + 12, 2048)  # 256 tokens x 2048 per slot, then the prompt


@pytest.mark.parametrize("name", ["pi0", "pi0_fast"])
def test_activation_checkpointing_lowers_the_peak(name: str) -> None:
    plain, checkpointed = checkpointing_peaks(grafted(name))
    assert checkpointed < 0.85 * plain, (checkpointed, plain)
