"""Tiny pi0.5 at the PaliGemma family's tiny geometry (graftcache.backbones.paligemma.Pi05TinyGeometry), with its
adaRMS gates opened so that a tiny pi0.5 sees its images.
"""

from __future__ import annotations

import torch

from graftcache.backbones.paligemma import Pi05TinyGeometry, paligemma_tiny_tokenizer, pi05_processors, pi05_tiny_sizes
from graftcache.backbones.tiny import TinyBuild, action_features, require_stats, visual_features


def pi05_tiny_config(tiny: TinyBuild, geometry: Pi05TinyGeometry, device: str):
    from lerobot.policies.pi05.configuration_pi05 import PI05Config

    return PI05Config(
        chunk_size=tiny.chunk_size, n_action_steps=tiny.chunk_size, num_inference_steps=tiny.num_steps,
        image_resolution=(geometry.image_size, geometry.image_size),
        max_state_dim=max(tiny.state_dim, 8), max_action_dim=max(tiny.action_dim, 8),
        tokenizer_max_length=geometry.tokenizer_max_length, device=device, dtype="float32",
        input_features=visual_features(tiny, geometry.image_size), output_features=action_features(tiny),
    )


def _open_adarms_gates(policy) -> None:
    """Random-init adaRMS starts with (near-)closed gates, so the expert ignores the prefix and a tiny
    pi0.5 barely sees its images. Open them: small random modulation, gate bias 1."""
    for module in policy.modules():
        dense = getattr(module, "dense", None)
        if type(module).__name__ == "PiGemmaRMSNorm" and dense is not None:
            torch.nn.init.normal_(dense.weight, std=0.02)
            torch.nn.init.zeros_(dense.bias)
            dense.bias.data[2 * module.dim:].fill_(1.0)


def build_tiny(tiny: TinyBuild, stats: dict | None, device: str):
    """Random-init tiny pi0.5, its lerobot pre/post processors (deterministic for `tiny.seed`) and its geometry (the
    tiny marker records it: lerobot hard-codes PaliGemma's sizes)."""
    from lerobot.policies.pi05.modeling_pi05 import PI05Policy

    geometry = Pi05TinyGeometry()
    config = pi05_tiny_config(tiny, geometry, device)
    with torch.random.fork_rng(devices=[]), pi05_tiny_sizes(geometry):
        torch.manual_seed(tiny.seed)
        policy = PI05Policy(config)
        _open_adarms_gates(policy)
    pre, post = pi05_processors(config, require_stats(stats), paligemma_tiny_tokenizer())
    return policy.to(device), pre, post, geometry

