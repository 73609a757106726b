"""SmolVLA's spec (graftcache.backbones.spec.BackboneSpec): data only, so that what reports read of a backbone
(its label, its released size) is read without importing its adapter, torch or lerobot."""

from __future__ import annotations

from graftcache.backbones.spec import BackboneSpec

SPEC = BackboneSpec(
    label="SmolVLA",
    lerobot_extra="smolvla",
    released_params=450_000_000,
    image_method="prepare_images",
    vision_slots=("vision_model", "connector"),
    lm_width="_vision_owner.config.text_config.hidden_size",
    module_paths={
        "language model": ("_vision_owner.text_model",),
        "action expert": ("policy.model.vlm_with_expert.lm_expert",),
        "state projection": ("policy.model.state_proj",),
        "action/time projections": tuple(f"policy.model.{m}" for m in (
            "action_in_proj", "action_out_proj", "action_time_mlp_in", "action_time_mlp_out")),
    },
    steps_field="num_steps",
    token_steps=("NewLineTaskProcessorStep", "TokenizerProcessorStep"),
    scaled_embeddings=True,
    cells_per_pass={"cpu": 1, "cuda": 4},
    can_recompute=True,
    compiled_forward="policy.model",
    attentions=("eager", "sdpa"),
)
