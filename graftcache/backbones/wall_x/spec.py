"""Wall-X's spec (graftcache.backbones.spec.BackboneSpec): data only, so that what reports read of a backbone
(its label, its released size) is read without importing its adapter, torch or lerobot."""

from __future__ import annotations

from graftcache.backbones.spec import BackboneSpec

SPEC = BackboneSpec(
    label="Wall-X",
    lerobot_extra="wallx",
    image_method="preprocess_inputs",
    vision_slots=("blocks", "merger"),
    lm_width="policy.model.config.text_config.hidden_size",
    module_paths={
        "patch embedding": ("_vision_owner.patch_embed",),
        "language model": ("policy.model.model",),
        "action head": ("policy.model.action_preprocessor",),
    },
    steps_field=None,
    prompt_uses_state=True,
    flow_time="data",
    can_recompute=True,
    lerobot_reaches=(
        "lerobot.policies.wall_x.modeling_wall_x._resize_wall_x_image_batch",
        "lerobot.policies.wall_x.modeling_wall_x._wall_x_resize_dimensions",
    ),
)
