"""pi0.5's spec (graftcache.backbones.spec.BackboneSpec): data only, so that what reports read of a backbone
(its label, its released size) is read without importing its adapter, torch or lerobot."""

from __future__ import annotations

from graftcache.backbones.spec import BackboneSpec

SPEC = BackboneSpec(
    label="pi0.5",
    lerobot_extra="pi",
    released_params=3_300_000_000,
    image_method="_preprocess_images",
    vision_slots=("vision_tower", "multi_modal_projector"),
    lm_width="_vision_owner.config.text_config.hidden_size",
    module_paths={
        "language model": ("_vision_owner.language_model",),
        "action expert": ("policy.model.paligemma_with_expert.gemma_expert",),
        "action/time projections": tuple(f"policy.model.{m}" for m in (
            "action_in_proj", "action_out_proj", "time_mlp_in", "time_mlp_out")),
    },
    steps_field="num_inference_steps",
    token_steps=("Pi05PrepareStateTokenizerProcessorStep", "TokenizerProcessorStep"),
    prompt_uses_state=True,
    cells_per_pass={"cpu": 1, "cuda": 1},
    can_recompute=True,
    compiled_forward="policy.model",
    attentions=("eager", "sdpa"),
    lerobot_reaches=(
        "lerobot.policies.pi05.modeling_pi05.PI05Policy._preprocess_images",
    ),
)
