"""An export's saved pipelines, as offline scoring prepares a batch and reads its chunk.

Preprocessor: rename -> the cell's features -> device (lerobot-eval overrides the first and last). The frames become
the cell's features under `observation.vis_feats.<policy camera>` (graftcache.export.features), as
graftcache.fit.loop.raw_batch holds them; the base policy's own preprocessing then runs inside the policy, through
its adapter's `prepare` (graftcache.export.modeling_graftcache), which grafted EO-1 and GR00T need to build their
prompts around cached features.

Postprocessor: the base policy's own. Its saved processors often need more than their JSON to load: tiny
checkpoints' tokenizers are local folders handed over as objects (graftcache.backbones.*._processor_overrides), which
lerobot cannot serialise, so the export saves one registered step naming the base policy, which loads them through
the backbone adapter and runs their steps.
"""

from __future__ import annotations

import functools
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from lerobot.processor import DeviceProcessorStep, ProcessorStep, ProcessorStepRegistry, RenameObservationsProcessorStep
from lerobot.processor.converters import (
    batch_to_transition,
    policy_action_to_transition,
    transition_to_batch,
    transition_to_policy_action,
)
from lerobot.processor.pipeline import PolicyProcessorPipeline, TransitionKey

from graftcache.errors import ExportError
from graftcache.export.features import CellFeatures, load_cell_features
from graftcache.graft import feature_key

STEP = "graftcache_base_postprocessor"
FEATURES_STEP = "graftcache_cell_features"
IMAGE_PREFIX = "observation.images."


@ProcessorStepRegistry.register(FEATURES_STEP)
@dataclass
class CellFeaturesStep(ProcessorStep):
    """Camera frames -> the cell's features, for every policy camera from the camera the cell mapped to it (the
    frames themselves leave the batch, as offline scoring never had them). `folder`: the export."""

    folder: str = ""
    device: str = "cpu"

    @functools.cached_property
    def config(self) -> dict[str, Any]:
        return json.loads((Path(self.folder) / "config.json").read_text())

    @functools.cached_property
    def features(self) -> CellFeatures:
        return load_cell_features(Path(self.folder), self.config, self.device)

    def __call__(self, transition: Any) -> Any:
        observation = dict(transition[TransitionKey.OBSERVATION])
        frames = {k: observation.pop(k) for k in list(observation) if k.startswith(IMAGE_PREFIX)}
        for policy_camera, camera in self.config["cameras"].items():
            key = IMAGE_PREFIX + camera
            if key not in frames:
                raise ExportError(f"{self.folder}: the observation has no {key} (it feeds policy camera "
                                  f"{policy_camera}); pass lerobot-eval a --rename_map that provides it")
            images = frames[key].to(self.features.encoder.device)
            with torch.no_grad():
                observation[feature_key(policy_camera)] = self.features(images if images.ndim == 4 else images[None])
        return {**transition, TransitionKey.OBSERVATION: observation}

    def transform_features(self, features: dict) -> dict:
        return features

    def get_config(self) -> dict[str, Any]:
        return {"folder": self.folder, "device": self.device}


@ProcessorStepRegistry.register(STEP)
@dataclass
class BasePostprocessorStep(ProcessorStep):
    """Runs the saved postprocessor of the base policy of `backbone` at `source`."""

    backbone: str = ""
    source: str = ""
    device: str = "cpu"

    @functools.cached_property
    def steps(self) -> list[ProcessorStep]:
        from graftcache.backbones import get_backbone

        _, post = get_backbone(self.backbone).saved_processors(self.source, self.device)
        return list(post.steps)

    def __call__(self, transition: Any) -> Any:
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


def export_pipelines(folder: str, backbone: str, source: str, device: str = "cpu") -> tuple[
        PolicyProcessorPipeline, PolicyProcessorPipeline]:
    """The (pre, post) pipelines the export at `folder` saves: rename -> the cell's features -> device; the base's
    postprocessor."""
    pre = PolicyProcessorPipeline(
        steps=[RenameObservationsProcessorStep(rename_map={}), CellFeaturesStep(folder, device),
               DeviceProcessorStep(device=device)],
        name="policy_preprocessor", to_transition=batch_to_transition, to_output=transition_to_batch)
    post = PolicyProcessorPipeline(
        steps=[BasePostprocessorStep(backbone, source, device)], name="policy_postprocessor",
        to_transition=policy_action_to_transition, to_output=transition_to_policy_action)
    return pre, post
