"""Scoring's cost: each batch's prefix (images + prompt through the frozen LM) is computed once and its KV cache
reused by every denoising step, as lerobot's `sample_actions` does; only the action expert runs per step."""

from __future__ import annotations

import pytest
import torch
from helpers.backbones import fixed_noise_time, grafted, raw_features

#: The parts counted (the LM that reads the prefix, the action expert): groups of the spec's `module_paths`.
PARTS = {"lm": "language model", "expert": "action expert"}


def _first_query(module: torch.nn.Module) -> torch.nn.Module:
    """The query projection of a decoder's first layer (the decoder itself or a model wrapping it)."""
    return next(m for n, m in module.named_modules() if n.endswith("layers.0.self_attn.q_proj"))


@pytest.mark.parametrize("name", ["smolvla", "pi05"])
@pytest.mark.parametrize("steps", [1, 5])
def test_the_prefix_runs_once_per_batch_whatever_the_denoising_steps(name: str, steps: int) -> None:
    adapter = grafted(name)
    batch = adapter.prepare(raw_features(adapter, 3))
    noise, _ = fixed_noise_time(adapter, 3)
    calls = dict.fromkeys(PARTS, 0)
    hooks = []
    groups = adapter._module_groups()
    for part, group in PARTS.items():
        layer = _first_query(groups[group])

        def count(*_, part=part) -> None:
            calls[part] += 1
        hooks.append(layer.register_forward_hook(count))
    try:
        with torch.no_grad():
            adapter.predict(batch, noise=noise, num_steps=steps)
    finally:
        for hook in hooks:
            hook.remove()
    assert calls == {"lm": 1, "expert": steps}
