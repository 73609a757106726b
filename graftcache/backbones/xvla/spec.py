"""X-VLA's spec (graftcache.backbones.spec.BackboneSpec): data only, so that what reports read of a backbone
(its label, its released size) is read without importing its adapter, torch or lerobot."""

from __future__ import annotations

from graftcache.backbones.spec import BackboneSpec

SPEC = BackboneSpec(
    label="X-VLA",
    lerobot_extra="xvla",
    image_method="_prepare_images",
    vision_slots=("vision_tower", "multi_modal_projector"),
    lm_width="_vision_owner.config.vision_config.projection_dim",
    module_paths={
        "language model": ("_vision_owner.language_model",),
        "action transformer": ("policy.model.transformer",),
    },
    steps_field="num_denoising_steps",
    token_steps=("TokenizerProcessorStep",),
    can_recompute=True,
    attentions=("sdpa",),  # lerobot builds its LM with transformers' sdpa attention
    lerobot_reaches=(
        "lerobot.policies.xvla.modeling_xvla.XVLAModel._get_target_dtype",
        "lerobot.policies.xvla.modeling_xvla.XVLAPolicy._build_model_inputs",
        "lerobot.policies.xvla.modeling_xvla.XVLAPolicy._prepare_action_targets",
        "lerobot.policies.xvla.modeling_xvla.XVLAPolicy._prepare_images",
        "lerobot.policies.xvla.modeling_xvla._is_vendored_florence_state_dict",
    ),
)
