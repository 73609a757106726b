"""Tiny pi0 at the PaliGemma family's tiny geometry (graftcache.backbones.paligemma.Pi05TinyGeometry)."""

from __future__ import annotations

import torch

from graftcache.backbones.paligemma import Pi05TinyGeometry, paligemma_tiny_tokenizer, pi05_processors, pi05_tiny_sizes
from graftcache.backbones.tiny import TinyBuild, action_features, require_stats, visual_features

MODELING = "lerobot.policies.pi0.modeling_pi0"
PROCESSOR = "lerobot.policies.pi0.processor_pi0"


def build_tiny(tiny: TinyBuild, stats: dict | None, device: str):
    """Random-init tiny pi0, its lerobot pre/post processors (deterministic for `tiny.seed`) and its geometry."""
    from lerobot.policies.pi0.configuration_pi0 import PI0Config
    from lerobot.policies.pi0.modeling_pi0 import PI0Policy

    geometry = Pi05TinyGeometry()
    config = PI0Config(
        chunk_size=tiny.chunk_size, n_action_steps=tiny.chunk_size, num_inference_steps=tiny.num_steps,
        image_resolution=(geometry.image_size, geometry.image_size),
        max_state_dim=max(tiny.state_dim, 8), max_action_dim=max(tiny.action_dim, 8),
        tokenizer_max_length=geometry.tokenizer_max_length, device=device, dtype="float32",
        input_features=visual_features(tiny, geometry.image_size), output_features=action_features(tiny),
    )
    with torch.random.fork_rng(devices=[]), pi05_tiny_sizes(geometry, MODELING):
        torch.manual_seed(tiny.seed)
        policy = PI0Policy(config)
    pre, post = pi05_processors(config, require_stats(stats), paligemma_tiny_tokenizer(), PROCESSOR,
                                "make_pi0_pre_post_processors")
    return policy.to(device), pre, post, geometry
