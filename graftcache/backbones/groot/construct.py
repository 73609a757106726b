"""Building GR00T N1.7 without its weights, released or tiny: lerobot's `GrootPolicy` on a base model config.

A lerobot GR00T checkpoint keeps only `GrootConfig`; its model is rebuilt by `GR00TN17.from_pretrained(
base_model_path)`, which downloads the base checkpoint (its `GR00TN17Config` and weights). `construct` builds the
policy with `GR00TN17.from_pretrained` patched (graftcache.backbones.patching) to build from a `GR00TN17Config`
without any weights (graftcache fills them from the checkpoint, lean): the base config is read from the base
checkpoint's config.json (a folder, or the local HF cache: `base_config`), is lerobot's mirror of
nvidia/GR00T-N1.7-3B's (`released_base_config`), or the tiny one (graftcache/backbones/groot/tiny.py).
"""

from __future__ import annotations

import contextlib
import json
from collections.abc import Iterator
from typing import Any

from graftcache.backbones.checkpoint import local_or_cached
from graftcache.backbones.patching import patched
from graftcache.backbones.tiny import TinyBuild, action_features, visual_features
from graftcache.errors import BackboneError


def base_config(path: str):
    """The GR00TN17Config of a base checkpoint (`GrootConfig.base_model_path`): a folder, or a hub id from the
    local HF cache (what lerobot's `GR00TN17.from_pretrained` would download)."""
    from lerobot.policies.groot.groot_n1_7 import GR00TN17Config

    folder = local_or_cached(path, "GR00T's base model config")
    try:
        return GR00TN17Config(**json.loads((folder / "config.json").read_text()))
    except (OSError, ValueError) as exc:
        raise BackboneError(f"{folder / 'config.json'}: not a GR00T N1.7 base config ({exc})") from None


@contextlib.contextmanager
def base_model(base) -> Iterator[None]:
    """`GR00TN17.from_pretrained` builds from `base` (a GR00TN17Config) with no weights while the block runs, with
    the overrides and trainable flags lerobot's GrootPolicy passes (transformers would set the overrides on the
    loaded config); the backbone is built from its config (`load_backbone_weights=False`, as lerobot does)."""
    from lerobot.policies.groot.groot_n1_7 import GR00TN17

    def build(cls, pretrained_model_name_or_path: str, **kwargs: Any):
        flags = {k: kwargs.pop(k) for k in ("tune_visual", "tune_llm", "tune_projector", "tune_diffusion_model",
                                            "tune_vlln")}
        loading = kwargs.pop("transformers_loading_kwargs", None)
        config = base.__class__(**{**base.to_dict(), **kwargs})
        model = cls(config, transformers_loading_kwargs=loading, load_backbone_weights=False)
        model.backbone.set_trainable_parameters(tune_visual=flags["tune_visual"], tune_llm=flags["tune_llm"],
                                                tune_top_llm_layers=config.tune_top_llm_layers)
        model.action_head.set_trainable_parameters(tune_projector=flags["tune_projector"],
                                                   tune_diffusion_model=flags["tune_diffusion_model"],
                                                   tune_vlln=flags["tune_vlln"])
        return model

    with patched(GR00TN17, from_pretrained=classmethod(build)):
        yield


def construct(config, base):
    """GrootPolicy(config) on the base model config `base`, no weights read."""
    from lerobot.policies.groot.modeling_groot import GrootPolicy

    with base_model(base):
        return GrootPolicy(config)


def groot_released_config(cameras: tuple[str, ...], image_size: int, state_dim: int, action_dim: int, device: str):
    """nvidia/GR00T-N1.7-3B fine-tuned on a dataset, as lerobot configures it (its defaults: chunk 40, state and
    action padded to 132, the new_embodiment tag)."""
    from lerobot.policies.groot.configuration_groot import GrootConfig

    tiny = TinyBuild(cameras=cameras, state_dim=state_dim, action_dim=action_dim)
    return GrootConfig(device=device, input_features=visual_features(tiny, image_size),
                       output_features=action_features(tiny))


def released_base_config():
    """nvidia/GR00T-N1.7-3B's GR00TN17Config as lerobot mirrors it (GR00T_N1_7_DEFAULTS; backbone
    nvidia/Cosmos-Reason2-2B, whose Qwen3-VL config lerobot hard-codes)."""
    from lerobot.policies.groot.groot_n1_7 import GR00TN17Config

    return GR00TN17Config()
