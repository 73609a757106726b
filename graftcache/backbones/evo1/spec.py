"""EVO1's spec (graftcache.backbones.spec.BackboneSpec): data only, so that what reports read of a backbone
(its label, its released size) is read without importing its adapter, torch or lerobot."""

from __future__ import annotations

from graftcache.backbones.spec import BackboneSpec

SPEC = BackboneSpec(
    label="EVO1",
    lerobot_extra="evo1",
    image_method="_collect_image_batches",
    vision_slots=("vision_tower", "multi_modal_projector"),
    lm_width="_vision_owner.config.text_config.hidden_size",
    module_paths={
        "language model": ("_vision_owner.language_model",),
        "action head": ("policy.model.action_head",),
    },
    steps_field="num_inference_timesteps",
    prompt_uses_state=True,
    flow_time="data",
)
