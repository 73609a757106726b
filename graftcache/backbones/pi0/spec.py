"""pi0's spec (graftcache.backbones.spec.BackboneSpec): data only, so that what reports read of a backbone
(its label, its released size) is read without importing its adapter, torch or lerobot."""

from __future__ import annotations

import dataclasses

from graftcache.backbones.pi05.spec import SPEC as PI05_SPEC

SPEC = dataclasses.replace(
    PI05_SPEC,
    label="pi0",
    module_paths={
        "language model": ("_vision_owner.language_model",),
        "action expert": ("policy.model.paligemma_with_expert.gemma_expert",),
        "state projection": ("policy.model.state_proj",),
        "action/time projections": tuple(f"policy.model.{m}" for m in (
            "action_in_proj", "action_out_proj", "action_time_mlp_in", "action_time_mlp_out")),
    },
    token_steps=("Pi0NewLineProcessor", "TokenizerProcessorStep"),
    prompt_uses_state=False,
    lerobot_reaches=(
        "lerobot.policies.pi0.modeling_pi0.PI0Policy._preprocess_images",
    ),
)
