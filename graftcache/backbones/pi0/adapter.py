"""pi0 (lerobot 0.6, PaliGemma gemma_2b + gemma_300m expert, no adaRMS) as a graftable backbone.

Vision path (modeling_pi0.py:297, 1000): as pi0.5's. `_preprocess_images` pads/resizes to 224 px and rescales to
[-1, 1]; `embed_image` = PaliGemma `get_image_features(...).pooler_output`: SigLIP So400m/14 (16x16 patches x 1152)
-> multi_modal_projector Linear(1152 -> 2048) = 256 tokens x 2048 per camera, no further scaling. The graft
replaces SigLIP with a pass-through and the projector with the graft projector.

What differs from pi0.5 (so this adapter differs from graftcache.backbones.pi05.adapter there and nowhere else): the
state is not in the prompt but a token of the expert's suffix (`state_proj`), so the prompt is the task alone
("<task>\\n", processor_pi0.py) and is tokenised once per task; the flow model takes the padded state
(`prepare_state`); time enters through `action_time_mlp_*`, not adaRMS.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch
from torch import nn

from graftcache.backbones.batches import TOKEN_MASK, TOKENS
from graftcache.backbones.paligemma import pi05_processors, pi05_tiny_sizes
from graftcache.backbones.pi0.spec import SPEC
from graftcache.backbones.pi0.tiny import MODELING, PROCESSOR
from graftcache.backbones.pi05.adapter import PI05Adapter


class PI0Adapter(PI05Adapter):
    name = "pi0"
    spec = SPEC

    # ------------------------------------------------------------------------------ construction
    @classmethod
    def _construct(cls, config, marker: dict | None) -> nn.Module:
        from lerobot.policies.pi0.modeling_pi0 import PI0Policy

        if marker is None:
            return PI0Policy(config)
        with pi05_tiny_sizes(marker["geometry"], MODELING):
            return PI0Policy(config)

    @classmethod
    def _make_processors(cls, config, stats: dict, marker: dict | None):
        return pi05_processors(config, stats, cls._tokenizer(marker), PROCESSOR, "make_pi0_pre_post_processors")

    # ----------------------------------------------------------------------------- policy loss
    def _flow_losses(self, batch: Mapping[str, Any], noise, time) -> torch.Tensor:
        policy = self.policy
        images, img_masks = policy._preprocess_images(batch)
        return policy.model.forward(images, img_masks, batch[TOKENS], batch[TOKEN_MASK], policy.prepare_state(batch),
                                    policy.prepare_action(batch), noise, time)
