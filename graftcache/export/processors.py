"""The base policy's own processors inside an export's saved pipelines, loaded the way graftcache loads them.

A base policy's saved processors often need more than their JSON to load: tiny checkpoints' tokenizers are local
folders handed over as objects (graftcache.backbones.*._processor_overrides), which lerobot cannot serialise. So an
export's pipelines hold one registered step naming the base policy, which loads its processors through the backbone
adapter and runs their steps, between the two steps lerobot-eval always overrides (rename, device).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any

from lerobot.processor import DeviceProcessorStep, ProcessorStep, ProcessorStepRegistry, RenameObservationsProcessorStep
from lerobot.processor.converters import (
    batch_to_transition,
    policy_action_to_transition,
    transition_to_batch,
    transition_to_policy_action,
)
from lerobot.processor.pipeline import PolicyProcessorPipeline

STEP = "graftcache_base_processors"


@ProcessorStepRegistry.register(STEP)
@dataclass
class BaseProcessorsStep(ProcessorStep):
    """Runs the saved `which` ("pre" | "post") processors of the base policy of `backbone` at `source`."""

    backbone: str = ""
    source: str = ""
    which: str = "pre"
    device: str = "cpu"

    @functools.cached_property
    def steps(self) -> list[ProcessorStep]:
        from graftcache.backbones import get_backbone

        pre, post = get_backbone(self.backbone).saved_processors(self.source, self.device)
        return list((pre if self.which == "pre" else post).steps)

    def __call__(self, transition: Any) -> Any:
        for step in self.steps:
            transition = step(transition)
        return transition

    def transform_features(self, features: dict) -> dict:
        for step in self.steps:
            features = step.transform_features(features)
        return features

    def get_config(self) -> dict[str, Any]:
        return {"backbone": self.backbone, "source": self.source, "which": self.which, "device": self.device}

    def reset(self) -> None:
        for step in self.steps:
            step.reset()


def export_pipelines(backbone: str, source: str, device: str = "cpu") -> tuple[PolicyProcessorPipeline,
                                                                                PolicyProcessorPipeline]:
    """The (pre, post) pipelines an export saves: rename -> the base's preprocessor -> device; the base's
    postprocessor."""
    pre = PolicyProcessorPipeline(
        steps=[RenameObservationsProcessorStep(rename_map={}), BaseProcessorsStep(backbone, source, "pre", device),
               DeviceProcessorStep(device=device)],
        name="policy_preprocessor", to_transition=batch_to_transition, to_output=transition_to_batch)
    post = PolicyProcessorPipeline(
        steps=[BaseProcessorsStep(backbone, source, "post", device)], name="policy_postprocessor",
        to_transition=policy_action_to_transition, to_output=transition_to_policy_action)
    return pre, post
