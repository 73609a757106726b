"""Tiny SmolVLA, built offline from graftcache/resources/tiny/smolvlm/.

SigLIP 96 wide x 2 layers at 128 px / patch 16 -> 8x8 patches, pixel shuffle 2 -> 4x4 = 16 tokens per camera,
Llama text model 192 wide x 4 layers, expert 144 wide (lerobot's 0.75).
"""

from __future__ import annotations

from graftcache.backbones.tiny import TinyBuild, action_features, build_seeded, visual_features
from graftcache.backbones.tiny_assets import SMOLVLM_DIR, SMOLVLM_GEOMETRY


def smolvla_tiny_config(tiny: TinyBuild, device: str):
    from lerobot.policies.smolvla.configuration_smolvla import SmolVLAConfig

    size = SMOLVLM_GEOMETRY["image_size"]
    return SmolVLAConfig(
        vlm_model_name=str(SMOLVLM_DIR), load_vlm_weights=False,
        num_vlm_layers=SMOLVLM_GEOMETRY["text_layers"],
        resize_imgs_with_padding=(size, size),
        chunk_size=tiny.chunk_size, n_action_steps=tiny.chunk_size, num_steps=tiny.num_steps,
        max_state_dim=max(tiny.state_dim, 8), max_action_dim=max(tiny.action_dim, 8),
        device=device,
        input_features=visual_features(tiny, size), output_features=action_features(tiny),
    )


def build_tiny(tiny: TinyBuild, stats: dict | None, device: str):
    """Random-init tiny SmolVLA and its processors (graftcache.backbones.tiny.build_seeded)."""
    from lerobot.policies.smolvla.modeling_smolvla import SmolVLAPolicy
    from lerobot.policies.smolvla.processor_smolvla import make_smolvla_pre_post_processors

    return build_seeded(tiny, stats, device, smolvla_tiny_config(tiny, device), SmolVLAPolicy,
                        make_smolvla_pre_post_processors)

