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
    lerobot_reaches=(
        "lerobot.policies.evo1.modeling_evo1.Evo1Policy._collect_image_batches",
        "lerobot.policies.evo1.modeling_evo1.Evo1Policy._compute_dtype",
        "lerobot.policies.evo1.modeling_evo1.Evo1Policy._compute_fused_tokens",
        "lerobot.policies.evo1.modeling_evo1.Evo1Policy._device",
        "lerobot.policies.evo1.modeling_evo1.Evo1Policy._get_embodiment_ids",
        "lerobot.policies.evo1.modeling_evo1.Evo1Policy._maybe_autocast",
        "lerobot.policies.evo1.modeling_evo1.Evo1Policy._normalize_task_batch",
        "lerobot.policies.evo1.modeling_evo1.Evo1Policy._prepare_actions",
        "lerobot.policies.evo1.modeling_evo1.Evo1Policy._prepare_inference_action_mask",
        "lerobot.policies.evo1.modeling_evo1.Evo1Policy._prepare_state",
        "lerobot.policies.evo1.flow_matching.FlowmatchingActionHead._expand_action_mask",
        "lerobot.policies.evo1.flow_matching.FlowmatchingActionHead._prepare_context",
        "lerobot.policies.evo1.flow_matching.FlowmatchingActionHead._project_actions",
        "lerobot.policies.evo1.internvl3_embedder.InternVL3Embedder._forward_vlm",
        "lerobot.policies.evo1.internvl3_embedder._batched_pixel_values",
    ),
)
