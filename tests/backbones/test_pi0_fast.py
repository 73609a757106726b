"""pi0-FAST as a backbone: its own policy loss (lerobot's cross-entropy on FAST tokens, greedy decoding for scoring)
and its FAST tokenizer. Its released geometry beside pi0's: tests/backbones/test_pi0.py."""

from __future__ import annotations

import itertools
import json

import numpy as np
import pytest
import torch
from helpers.backbones import fixed_noise_time, grafted, raw_features, raw_images, tiny
from scipy.fft import dct, idct

from graftcache.backbones import load_backbone
from graftcache.backbones.pi0_fast.fast import FAST_DIR
from graftcache.backbones.policy_loss import FlowLoss
from graftcache.errors import BackboneError

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
    assert not isinstance(adapter, FlowLoss) and not hasattr(adapter, "_flow_losses")  # a token loss only


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
