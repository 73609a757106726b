"""pi0-FAST's spec (graftcache.backbones.spec.BackboneSpec): data only, so that what reports read of a backbone
(its label, its released size) is read without importing its adapter, torch or lerobot."""

from __future__ import annotations

from graftcache.backbones.spec import BackboneSpec

SPEC = BackboneSpec(
    label="pi0-FAST",
    lerobot_extra="pi",
    released_params=2_900_000_000,
    image_method="_preprocess_images",
    vision_slots=("vision_tower", "multi_modal_projector"),
    lm_width="_vision_owner.config.text_config.hidden_size",
    module_paths={"language model": ("_vision_owner.language_model",),
                  "LM head": ("policy.model.paligemma_with_expert.paligemma.lm_head",)},
    steps_field="max_decoding_steps",
    token_steps=("Pi0FastPrepareStateAndLanguageTokenizerProcessorStep", "TokenizerProcessorStep",
                 "ActionTokenizerProcessorStep"),
    prompt_uses_state=True,
    loss_per_sample=False,
    flow_time=None,
    can_recompute=True,
    compiled_forward="policy.model",
    attentions=("sdpa", "eager"),  # lerobot leaves pi0-FAST's Gemma at transformers' sdpa
    lerobot_reaches=(
        "lerobot.policies.pi0_fast.modeling_pi0_fast.PI0FastPolicy._preprocess_images",
    ),
)
