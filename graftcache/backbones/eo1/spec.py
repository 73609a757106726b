"""EO-1's spec (graftcache.backbones.spec.BackboneSpec): data only, so that what reports read of a backbone
(its label, its released size) is read without importing its adapter, torch or lerobot."""

from __future__ import annotations

from graftcache.backbones.spec import BackboneSpec

#: The processor step that tokenises the prompt with the images (one of the spec's `token_steps`).
QWEN_STEP = "EO1QwenProcessorStep"

SPEC = BackboneSpec(
    label="EO-1",
    lerobot_extra="eo1",
    image_method="_get_model_inputs",
    vision_slots=("blocks", "merger"),
    lm_width="policy.model.vlm_backbone.config.text_config.hidden_size",
    module_paths={
        "patch embedding": ("_vision_owner.patch_embed",),
        "language model": ("policy.model.vlm_backbone.model.language_model",),
        "action head": tuple(f"policy.model.{m}" for m in (
            "state_proj", "action_in_proj", "action_out_proj", "action_time_mlp_in", "action_time_mlp_out")),
    },
    steps_field="num_denoise_steps",
    token_steps=("EO1ConversationTemplateStep", QWEN_STEP),
    prompt_uses_state=True,
    attentions=("sdpa",),  # lerobot builds its LM with transformers' sdpa attention
    lerobot_reaches=(
        "lerobot.policies.eo1.modeling_eo1.EO1Policy._get_model_inputs",
        "lerobot.policies.eo1.processor_eo1.EO1QwenProcessorStep._processor",
    ),
)
