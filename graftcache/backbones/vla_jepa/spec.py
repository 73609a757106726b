"""VLA-JEPA's spec (graftcache.backbones.spec.BackboneSpec): data only, so that what reports read of a backbone
(its label, its released size) is read without importing its adapter, torch or lerobot."""

from __future__ import annotations

from graftcache.backbones.spec import BackboneSpec

SPEC = BackboneSpec(
    label="VLA-JEPA",
    lerobot_extra="vla-jepa",
    image_method="_prepare_model_inputs",
    vision_slots=("blocks", "merger"),
    lm_width="_qwen.config.text_config.hidden_size",
    module_paths={
        "patch embedding": ("_vision_owner.patch_embed", "_vision_owner.pos_embed"),
        "deepstack mergers": ("_vision_owner.deepstack_merger_list",),
        "language model": ("_qwen.language_model",),
        "action head": ("policy.model.action_model",),
    },
    steps_field="num_inference_timesteps",
    prompt_uses_state=True,
    flow_time="data",
    can_recompute=True,
    attentions=("sdpa",),  # lerobot builds its LM with transformers' sdpa attention
    lerobot_reaches=(
        "lerobot.policies.vla_jepa.modeling_vla_jepa.VLAJEPAPolicy._prepare_model_inputs",
        "lerobot.policies.vla_jepa.modeling_vla_jepa._get_autocast_context",
    ),
)
