"""SmolVLA as a backbone: what is its own (the loss falls on the tiny policy, its causal action expert keeps padded
steps out of the loss, how much activation checkpointing saves). What every backbone does alike is
tests/backbones/test_contract.py; what it shares with the PaliGemma policies, tests/backbones/test_adapters.py."""

from __future__ import annotations

import pytest
import torch
from helpers.backbones import activation_checkpointing_peaks, fixed_noise_time, grafted, raw_features

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # tests/fixtures/torch_threads.py


def test_loss_falls_on_tiny_smolvla() -> None:
    adapter = grafted("smolvla")
    batch = adapter.prepare(raw_features(adapter, 8))
    noise, time = fixed_noise_time(adapter, 8)
    optimiser = torch.optim.Adam(adapter.projector.parameters(), lr=1e-2)
    adapter.policy.train()
    losses = []
    for _ in range(12):
        loss = adapter.loss(batch, noise, time).mean()
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
        losses.append(loss.item())
    assert losses[-1] < 0.85 * losses[0]


def test_padded_action_targets_do_not_change_the_smolvla_loss() -> None:
    """SmolVLA's action expert is causal over the chunk, so padded steps (at the end) cannot leak in."""
    adapter = grafted("smolvla")
    raw = raw_features(adapter, 4)
    noise, time = fixed_noise_time(adapter, 4)
    with torch.no_grad():
        reference = adapter.loss(adapter.prepare(raw), noise, time)
        raw["action"][0, -3:] += 5.0  # padded steps of sample 0
        padded_changed = adapter.loss(adapter.prepare(raw), noise, time)
        raw["action"][0, 0] += 5.0  # a real step
        real_changed = adapter.loss(adapter.prepare(raw), noise, time)
    assert torch.equal(padded_changed, reference)
    assert real_changed[0] != reference[0]


def test_activation_checkpointing_lowers_the_peak() -> None:
    plain, checkpointed = activation_checkpointing_peaks(grafted("smolvla"))
    assert checkpointed < 0.85 * plain, (checkpointed, plain)  # measured: 80% of the plain step's peak
