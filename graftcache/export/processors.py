"""An export's saved pipelines, as offline scoring prepares a batch and reads its chunk.

Preprocessor: rename -> the cell's cameras checked -> device (lerobot-eval overrides the first and last). The frames
stay frames here: lerobot runs the preprocessor at every step, also while the policy still has queued actions, so
the policy turns them into the cell's features (graftcache.export.features.CellFeatures.observe) only when it
predicts a chunk (graftcache.export.modeling_graftcache); the encoder ran at every step before, which was most of a
simulated step's time. The base policy's own preprocessing then runs inside the policy too, through its adapter's
`prepare`, which grafted EO-1 and GR00T need to build their prompts around cached features.

Postprocessor: the base policy's own. Its saved processors often need more than their JSON to load: tiny
checkpoints' tokenizers are local folders handed over as objects (graftcache.backbones.*._processor_overrides), which
lerobot cannot serialise, so the export saves one registered step naming the base policy, which loads them through
the backbone adapter and runs their steps. The policy emits the normalised actions offline scoring computes, at the
dataset's action width; a base policy whose own `select_action` emits another width has its postprocessor expect that
one (EVO1: padded to `max_action_dim`, unnormalised there and cut back), so the step hands the actions over as the
adapter's `postprocessor_input` says, as offline scoring's `unnormalize` does.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field
from typing import Any

from lerobot.processor import DeviceProcessorStep, ProcessorStep, ProcessorStepRegistry, RenameObservationsProcessorStep
from lerobot.processor.converters import (
    batch_to_transition,
    policy_action_to_transition,
    transition_to_batch,
    transition_to_policy_action,
)
from lerobot.processor.pipeline import PolicyProcessorPipeline, TransitionKey

from graftcache.export.features import check_cameras

STEP = "graftcache_base_postprocessor"
FEATURES_STEP = "graftcache_cell_features"


@ProcessorStepRegistry.register(FEATURES_STEP)
@dataclass
class CellFeaturesStep(ProcessorStep):
    """Checks that the observation holds a frame for every camera the cell reads (one line naming the export's run,
    the camera and `--rename_map` otherwise), before any step runs; the frames pass on to the policy, which computes
    the features. It carries the cell's cameras (policy camera -> the cache's camera) itself, not the path of the
    export, so a moved or copied export checks what it runs. `device`: kept for lerobot's device overrides."""

    run_id: str = ""
    cameras: dict[str, str] = field(default_factory=dict)
    device: str = "cpu"

    def __call__(self, transition: Any) -> Any:
        check_cameras(transition[TransitionKey.OBSERVATION], self.cameras, f"the export of run {self.run_id}")
        return transition

    def transform_features(self, features: dict) -> dict:
        return features

    def get_config(self) -> dict[str, Any]:
        return {"run_id": self.run_id, "cameras": dict(self.cameras), "device": self.device}


@ProcessorStepRegistry.register(STEP)
@dataclass
class BasePostprocessorStep(ProcessorStep):
    """Runs the saved postprocessor of the base policy of `backbone` at `source` on the export's actions, handed
    over at the width it takes (the adapter's `postprocessor_input`)."""

    backbone: str = ""
    source: str = ""
    device: str = "cpu"

    @functools.cached_property
    def adapter(self) -> type:
        from graftcache.backbones import get_backbone

        return get_backbone(self.backbone)

    @functools.cached_property
    def config(self) -> Any:
        return self.adapter.saved_config(self.source, self.device)

    @functools.cached_property
    def steps(self) -> list[ProcessorStep]:
        _, post = self.adapter.saved_processors(self.source, self.device)
        return list(post.steps)

    def __call__(self, transition: Any) -> Any:
        action = transition.get(TransitionKey.ACTION)
        if action is not None:
            transition = {**transition, TransitionKey.ACTION: self.adapter.postprocessor_input(self.config, action)}
        for step in self.steps:
            transition = step(transition)
        return transition

    def transform_features(self, features: dict) -> dict:
        for step in self.steps:
            features = step.transform_features(features)
        return features

    def get_config(self) -> dict[str, Any]:
        return {"backbone": self.backbone, "source": self.source, "device": self.device}

    def reset(self) -> None:
        for step in self.steps:
            step.reset()


def export_pipelines(run_id: str, cameras: dict[str, str], backbone: str, source: str, device: str = "cpu") -> tuple[
        PolicyProcessorPipeline, PolicyProcessorPipeline]:
    """The (pre, post) pipelines the export of run `run_id` saves: rename -> the cell's `cameras` checked -> device;
    the base's postprocessor."""
    pre = PolicyProcessorPipeline(
        steps=[RenameObservationsProcessorStep(rename_map={}), CellFeaturesStep(run_id, cameras, device),
               DeviceProcessorStep(device=device)],
        name="policy_preprocessor", to_transition=batch_to_transition, to_output=transition_to_batch)
    post = PolicyProcessorPipeline(
        steps=[BasePostprocessorStep(backbone, source, device)], name="policy_postprocessor",
        to_transition=policy_action_to_transition, to_output=transition_to_policy_action)
    return pre, post
