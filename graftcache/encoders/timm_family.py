"""Encoders built with timm: registry entries (the wheel CNNs) and parametric `timm:<model name>`.

Weights go through timm's `pretrained_cfg_overlay` rather than a raw load_state_dict, so timm's
checkpoint filters run (e.g. DINOv2's 518 px position table is resampled to the input size). The load
is strict: timm turns strictness off whenever the requested class count differs from its config's,
so the model is built with the class count of the file's own classifier (0 for a headless file) and
the overlay says the same; a file that leaves any weight unset, or holds weights the model lacks, is
an EncoderError naming the file and the first such keys. A hub id is resolved to a file in the local
HF cache first, so the file that is hashed is the file that is loaded.
"""

from __future__ import annotations

import pickle
from collections.abc import Callable
from pathlib import Path
from typing import Any

import timm
import torch
from safetensors import SafetensorError
from torch import nn

from graftcache.encoders.encoder import Encoder, feature_map_to_grid, tokens_to_grid
from graftcache.encoders.loading import (
    hub_snapshot,
    key_mismatch,
    missing_hub_weights,
    require_file,
    seeded,
    sha256_state_dict,
)
from graftcache.encoders.spec import INTERPOLATIONS, EncoderSpec, LoadRequest, weights_info
from graftcache.errors import EncoderError, first_line
from graftcache.hashing import sha256_file

CNN_TOKENS = "timm forward_features(): last feature map, before global pooling and head"
VIT_TOKENS = "timm forward_features(): patch tokens after the final norm; prefix tokens dropped"
VIT_PRENORM_TOKENS = ("timm forward_features(): patch tokens BEFORE any final norm (this model normalises only "
                      "the pooled vector, fc_norm); prefix tokens dropped")
HUB_FILES = ("model.safetensors", "pytorch_model.bin")

DefaultWeights = Callable[[EncoderSpec], tuple[nn.Module, dict[str, Any]]]


class TimmEncoder(Encoder):
    """forward_features, then prefix tokens dropped (ViTs) or the last feature map permuted (CNNs)."""

    def _grid(self, x: torch.Tensor) -> torch.Tensor:
        f = self.model.forward_features(x)
        if f.ndim == 3:
            return tokens_to_grid(f, self.spec.prefix_tokens, self.spec.grid)
        return f if getattr(self.model, "output_fmt", "NCHW") == "NHWC" else feature_map_to_grid(f)


def create(spec: EncoderSpec, file: Path | None = None) -> nn.Module:
    """The timm architecture at the spec's input size; with `file`, strictly loaded through timm's filters."""
    kwargs: dict[str, Any] = {}
    if _pretrained_cfg(spec.model_id).get("fixed_input_size"):
        kwargs["img_size"] = spec.image_size  # ViTs: position table sized (or resampled) for the input
    if file is None:
        return timm.create_model(spec.model_id, pretrained=False, **kwargs)
    state = _read_state(spec, file)
    classes = _head_classes(spec.model_id, state)
    try:
        return timm.create_model(spec.model_id, pretrained=True, num_classes=classes,
                                 pretrained_cfg_overlay={"state_dict": state, "num_classes": classes}, **kwargs)
    except (RuntimeError, KeyError, ValueError) as e:
        expected = timm.create_model(spec.model_id, pretrained=False, num_classes=classes, **kwargs).state_dict()
        raise EncoderError(f"encoder {spec.name!r}: {file} does not fit timm {spec.model_id}: "
                           f"{key_mismatch(expected, state, e)}") from None


def _read_state(spec: EncoderSpec, file: Path) -> dict[str, torch.Tensor]:
    """The file's tensors as timm reads a checkpoint (EMA weights preferred, `module.` prefixes stripped);
    a file that is not what its name says is a one-line error naming it."""
    try:
        return timm.models.load_state_dict(str(file))
    except (SafetensorError, pickle.UnpicklingError, RuntimeError, EOFError) as e:
        raise EncoderError(f"encoder {spec.name!r}: {file} is not a readable weights file "
                           f"({first_line(e)})") from None


def _head_classes(model_name: str, state: dict[str, torch.Tensor]) -> int:
    """Output classes of the classifier the file holds (timm's config names it), 0 for a headless file."""
    names = _pretrained_cfg(model_name).get("classifier") or ()
    for name in (names,) if isinstance(names, str) else names:
        weight = state.get(f"{name}.weight")
        if weight is not None:
            return int(weight.shape[0])
    return 0


def load_hub(spec: EncoderSpec) -> tuple[nn.Module, dict[str, Any]]:
    """Default weights: the timm model's hub repo, from the local HF cache only."""
    repo = _pretrained_cfg(spec.model_id).get("hf_hub_id")
    if not repo:
        raise EncoderError(f"encoder {spec.name!r}: timm lists no hub weights for {spec.model_id}; "
                           f"pass --weights PATH or --random-init")
    found = hub_snapshot(repo)
    names = (_pretrained_cfg(spec.model_id).get("hf_hub_filename") or HUB_FILES[0], *HUB_FILES)
    files = [found[0] / n for n in names if (found[0] / n).is_file()] if found else []
    if not files:
        raise missing_hub_weights(spec, repo, "weights (" + " / ".join(dict.fromkeys(names)) + ")")
    model = create(spec, files[0])
    return model, weights_info("hub", f"{repo}@{found[1]}", sha256_file(files[0]))


def build(spec: EncoderSpec, req: LoadRequest, *, default: DefaultWeights = load_hub) -> TimmEncoder:
    """Builder for timm entries: random init, a safetensors file, else `default` (hub cache or wheel)."""
    info: dict[str, Any] | None = None
    if req.random_init:
        with seeded(req.init_seed):
            model = create(spec)
    elif req.weights is not None:
        path = require_file(spec, req.weights)
        model = create(spec, path)
        info = weights_info("file", str(path), sha256_file(path))
    else:
        model, info = default(spec)
    model.reset_classifier(0)
    if info is None:  # random init: hash the headless weights the features come from
        info = weights_info("random-init", spec.model_id, sha256_state_dict(model.state_dict()), seed=req.init_seed)
    return TimmEncoder(spec, model, info)


def resolve(name: str, model_name: str) -> EncoderSpec:
    """Spec of `timm:<model name>` at its pretrained input size, with grid/width measured on the meta device."""
    if not timm.is_model(model_name):
        raise EncoderError(f"encoder {name!r}: {model_name!r} is not a timm model (see timm.list_models())")
    cfg = _pretrained_cfg(model_name, name)
    if "input_size" not in cfg:
        raise EncoderError(f"encoder {name!r}: timm has no pretrained config (input size, mean/std) for {model_name}")
    if cfg.get("interpolation") not in INTERPOLATIONS:
        raise EncoderError(f"encoder {name!r}: timm interpolation {cfg.get('interpolation')!r} is not supported")
    size = int(cfg["input_size"][-1])
    probe = EncoderSpec(name, "timm", model_name, size, tuple(cfg["mean"]), tuple(cfg["std"]), cfg["interpolation"],
                        (0, 0), 0, 0, "", "")
    with torch.device("meta"):
        model = create(probe)
        out = model.forward_features(torch.empty(1, 3, size, size))
    if out.ndim == 3:
        prefix = int(getattr(model, "num_prefix_tokens", 0))
        grid, width = tuple(int(v) for v in model.patch_embed.grid_size), int(out.shape[-1])
        tokens = VIT_PRENORM_TOKENS if isinstance(getattr(model, "norm", None), nn.Identity) else VIT_TOKENS
    else:
        nhwc = getattr(model, "output_fmt", "NCHW") == "NHWC"
        prefix, tokens = 0, CNN_TOKENS
        grid = (int(out.shape[1]), int(out.shape[2])) if nhwc else (int(out.shape[2]), int(out.shape[3]))
        width = int(out.shape[-1] if nhwc else out.shape[1])
    hub = cfg.get("hf_hub_id")
    return EncoderSpec(name=name, library="timm", model_id=model_name, image_size=size, mean=probe.mean,
                       std=probe.std, interpolation=probe.interpolation, grid=grid, width=width,
                       prefix_tokens=prefix, pretrained_source=f"hub:{hub}" if hub else "none", tokens=tokens)


def _pretrained_cfg(model_name: str, name: str | None = None) -> dict[str, Any]:
    try:
        cfg = timm.models.get_pretrained_cfg(model_name)
    except RuntimeError as e:
        raise EncoderError(f"encoder {name or model_name!r}: {e}") from None
    return cfg.to_dict() if cfg is not None else {}
