"""Scoring's cost: each batch's prefix (images + prompt through the frozen LM) is computed once and its KV cache
reused by every denoising step, as lerobot's `sample_actions` does; only the action expert runs per step."""

from __future__ import annotations

import pytest
import torch
from helpers.backbones import fixed_noise_time, grafted, raw_features

#: backbone -> (the LM that reads the prefix, the action expert), as attribute paths from the policy
PARTS = {
    "smolvla": ("model.vlm_with_expert.vlm.model.text_model", "model.vlm_with_expert.lm_expert"),
    "pi05": ("model.paligemma_with_expert.paligemma.model.language_model",
             "model.paligemma_with_expert.gemma_expert.model"),
}


@pytest.mark.parametrize("name", ["smolvla", "pi05"])
@pytest.mark.parametrize("steps", [1, 5])
def test_the_prefix_runs_once_per_batch_whatever_the_denoising_steps(name: str, steps: int) -> None:
    adapter = grafted(name)
    batch = adapter.prepare(raw_features(adapter, 3))
    noise, _ = fixed_noise_time(adapter, 3)
    calls = {"lm": 0, "expert": 0}
    hooks = []
    for part, path in zip(calls, PARTS[name]):
        module = adapter.policy.get_submodule(path)
        layer = module.layers[0].self_attn.q_proj

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
