"""GR00T N1.7's spec (graftcache.backbones.spec.BackboneSpec): data only, so that what reports read of a backbone
(its label, its released size) is read without importing its adapter, torch or lerobot."""

from __future__ import annotations

from graftcache.backbones.spec import BackboneSpec

#: The processor step that encodes the prompt and images for the VLM (the spec's one `token_steps`).
VLM_STEP = "GrootN17VLMEncodeStep"

SPEC = BackboneSpec(
    label="GR00T N1.7",
    image_method="_filter_groot_inputs",
    vision_slots=("blocks", "merger"),
    lm_width="_groot.backbone.model.config.text_config.hidden_size",
    module_paths={
        "patch embedding": ("_vision_owner.patch_embed",),
        "deepstack mergers": ("_vision_owner.deepstack_merger_list",),
        "language model": ("_qwen.language_model",),
        "action head": ("_groot.action_head",),
    },
    steps_field="num_inference_timesteps",
    token_steps=(VLM_STEP,),
    prompt_uses_state=True,
    flow_time="data",
    attentions=("sdpa",),  # lerobot builds its LM with transformers' sdpa attention
    lerobot_reaches=(
        "lerobot.policies.groot.modeling_groot.GrootPolicy._filter_groot_inputs",
        "lerobot.policies.groot.modeling_groot.GrootPolicy._groot_model",
        "lerobot.policies.groot.processor_groot.GrootN17PackInputsStep._ordered_image_keys",
        "lerobot.policies.groot.processor_groot.GrootN17VLMEncodeStep._build_sample_images",
        "lerobot.policies.groot.processor_groot.GrootN17VLMEncodeStep._registry_name",
        "lerobot.policies.groot.processor_groot._load_n1_7_checkpoint_processor_assets",
        "lerobot.policies.groot.processor_groot._to_uint8_np_bthwc",
    ),
)
