"""Encoders built with transformers: registry entries (hand-written configs = the released
config.json of each checkpoint, since AutoConfig would need the hub) and parametric `hf:<id or folder>`.

Weights always go through `from_pretrained` (a folder, or `None` + a safetensors state_dict), so
transformers' own key handling applies (prefix stripping, text towers ignored); a checkpoint that
leaves any vision weight uninitialised is an error instead of a warning.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
from safetensors import SafetensorError
from torch import nn

from graftcache.encoders.encoder import Encoder, feature_map_to_grid, tokens_to_grid
from graftcache.encoders.hf_archs import HFArch, arch_of
from graftcache.encoders.loading import (
    hf_weight_files,
    hub_snapshot,
    missing_hub_weights,
    read_safetensors,
    require_file,
    seeded,
    sha256_files,
    sha256_state_dict,
)
from graftcache.encoders.spec import EncoderSpec, LoadRequest, weights_info
from graftcache.errors import EncoderError, first_line
from graftcache.hashing import sha256_file

_RESAMPLE = {2: "bilinear", 3: "bicubic"}  # PIL resample codes in preprocessor_config.json


class HFEncoder(Encoder):
    """last_hidden_state, then prefix tokens dropped (ViTs) or the feature map permuted (ResNet)."""

    def __init__(self, spec: EncoderSpec, model: nn.Module, weights_info: dict[str, Any], arch: HFArch) -> None:
        super().__init__(spec, model, weights_info)
        trained_size = getattr(model.config, "image_size", spec.image_size)
        interpolate = arch.interpolate_kwarg and trained_size != spec.image_size
        self._kwargs = {"interpolate_pos_encoding": True} if interpolate else {}

    def _grid(self, x: torch.Tensor) -> torch.Tensor:
        h = self.model(pixel_values=x, **self._kwargs).last_hidden_state
        return feature_map_to_grid(h) if h.ndim == 4 else tokens_to_grid(h, self.spec.prefix_tokens, self.spec.grid)


def build(spec: EncoderSpec, req: LoadRequest, *, arch: HFArch, config: Callable[[], Any]) -> HFEncoder:
    """Random init from `config()`, a safetensors file or model folder, else the default folder
    (`spec.model_id` as a local folder, or its snapshot in the local HF cache)."""
    if req.random_init:
        with seeded(req.init_seed):
            model = arch.model_class()(config())
        info = weights_info("random-init", spec.model_id, sha256_state_dict(model.state_dict()), seed=req.init_seed)
    elif req.weights is not None and Path(req.weights).is_dir():
        model, info = _from_folder(spec, arch, Path(req.weights), "file", str(req.weights))
    elif req.weights is not None:
        path = require_file(spec, Path(req.weights))
        model = _load(spec, arch, path, None, config=config(), state_dict=read_safetensors(spec, path))
        info = weights_info("file", str(path), sha256_file(path))
    else:
        folder, source, ref = default_folder(spec)
        model, info = _from_folder(spec, arch, folder, source, ref)
    return HFEncoder(spec, model, info, arch)


def default_folder(spec: EncoderSpec) -> tuple[Path, str, str]:
    """(folder, weights source, ref): a local folder as given, else the hub snapshot in the local cache."""
    local = Path(spec.model_id)
    if local.is_absolute():  # hf:<folder> specs store the resolved folder; registry entries store hub ids
        return local, "file", str(local)
    found = hub_snapshot(spec.model_id)
    if found is None or not hf_weight_files(found[0]):
        raise missing_hub_weights(spec, spec.model_id, "a snapshot with config.json and model weights")
    return found[0], "hub", f"{spec.model_id}@{found[1]}"


def build_parametric(spec: EncoderSpec, req: LoadRequest) -> HFEncoder:
    """Builder for `hf:` names: the architecture and config come from the resolved folder itself."""
    folder = _config_folder(spec.name, spec.model_id)
    arch = arch_of(_model_type(folder, spec.name), spec.name)
    return build(spec, req, arch=arch, config=lambda: arch.config_class().from_pretrained(folder))


def resolve(name: str, ref: str) -> EncoderSpec:
    """Spec of `hf:<hub id or folder>` from its config.json and preprocessor_config.json
    (input size = the processor's output size; grid and width measured on the meta device)."""
    folder = _config_folder(name, ref)
    arch = arch_of(_model_type(folder, name), name)
    config = arch.config_class().from_pretrained(folder)
    proc_file = folder / "preprocessor_config.json"
    if not proc_file.is_file():
        raise EncoderError(f"encoder {name!r}: {proc_file} is missing; the preprocessing (size, mean/std, "
                           f"resample) cannot be known without it")
    size, mean, std, interpolation = processor_recipe(json.loads(proc_file.read_text()), str(proc_file))
    grid, width = probe_grid(arch, config, size)
    local = Path(ref).expanduser().is_dir()
    model_id = str(folder.resolve()) if local else ref
    return EncoderSpec(name=name, library="transformers", model_id=model_id, image_size=size, mean=mean, std=std,
                       interpolation=interpolation, grid=grid, width=width, prefix_tokens=arch.prefix(config),
                       pretrained_source=("folder:" if local else "hub:") + model_id, tokens=arch.tokens)


def processor_recipe(proc: dict[str, Any], where: str) -> tuple[int, tuple, tuple, str]:
    """(input size, mean, std, interpolation) from an image processor's JSON: the final output size
    (crop_size when it center-crops, else size), without the crop itself."""
    key = "crop_size" if proc.get("do_center_crop") and proc.get("crop_size") else "size"
    size = _square(proc.get(key), where, key)
    if proc.get("resample") not in _RESAMPLE:
        raise EncoderError(f"{where}: resample {proc.get('resample')!r} not supported (2 bilinear, 3 bicubic)")
    if proc.get("do_normalize", True):
        if "image_mean" not in proc or "image_std" not in proc:
            raise EncoderError(f"{where}: image_mean/image_std missing")
        mean, std = tuple(float(v) for v in proc["image_mean"]), tuple(float(v) for v in proc["image_std"])
    else:
        mean, std = (0.0, 0.0, 0.0), (1.0, 1.0, 1.0)
    return size, mean, std, _RESAMPLE[proc["resample"]]


def probe_grid(arch: HFArch, config: Any, size: int) -> tuple[tuple[int, int], int]:
    """Grid and width of the model's tokens at `size`, from a forward pass on the meta device."""
    prefix = arch.prefix(config)
    kwargs = {"interpolate_pos_encoding": True} if arch.interpolate_kwarg else {}
    with torch.device("meta"):
        h = arch.model_class()(config)(pixel_values=torch.empty(1, 3, size, size), **kwargs).last_hidden_state
    if h.ndim == 4:
        return (int(h.shape[2]), int(h.shape[3])), int(h.shape[1])
    patch = config.patch_size
    grid = (size // patch, size // patch)
    if h.shape[1] != prefix + grid[0] * grid[1]:
        raise EncoderError(f"{type(config).__name__}: {h.shape[1]} tokens at {size} px, expected {prefix}+{grid}")
    return grid, int(h.shape[-1])


def _from_folder(spec: EncoderSpec, arch: HFArch, folder: Path, source: str, ref: str) -> tuple[nn.Module, dict]:
    files = hf_weight_files(folder)
    if not files:
        raise EncoderError(f"encoder {spec.name!r}: no model.safetensors / pytorch_model.bin in {folder}")
    model = _load(spec, arch, folder, folder)
    return model, weights_info(source, ref, sha256_files(files))


def _load(spec: EncoderSpec, arch: HFArch, origin: Path, *args: Any, **kwargs: Any) -> nn.Module:
    """from_pretrained in fp32, failing on any vision weight the checkpoint does not provide."""
    try:
        model, info = arch.model_class().from_pretrained(*args, output_loading_info=True, dtype=torch.float32,
                                                         **kwargs)
    except (OSError, RuntimeError, ValueError, SafetensorError) as e:
        raise EncoderError(f"encoder {spec.name!r}: {origin} does not load into {arch.model_cls}: "
                           f"{first_line(e)}") from e
    # transformers 5 reports sets (mismatched entries are (key, checkpoint shape, model shape)); sorted for a stable
    # message
    missing = sorted(info["missing_keys"]) + sorted(k for k, *_ in info["mismatched_keys"])
    if missing:
        unexpected = sorted(info["unexpected_keys"])
        extra = f"; {len(unexpected)} unexpected (first: {', '.join(unexpected[:3])})" if unexpected else ""
        raise EncoderError(f"encoder {spec.name!r}: {origin} leaves {len(missing)} weights of {arch.model_cls} "
                           f"unset (first: {', '.join(missing[:3])}){extra}; is it a {spec.model_id} checkpoint?")
    return model


def _config_folder(name: str, ref: str) -> Path:
    local = Path(ref).expanduser()
    found = (local, "") if local.is_dir() else hub_snapshot(ref)
    if found is None or not (found[0] / "config.json").is_file():
        where = local if local.is_dir() else f"the local HF cache (models--{ref.replace('/', '--')})"
        raise EncoderError(f"encoder {name!r}: no config.json for {ref!r} in {where}; nothing is downloaded. Give a "
                           f"local model folder, or put the model in the HF cache")
    return found[0]


def _model_type(folder: Path, name: str) -> str:
    model_type = json.loads((folder / "config.json").read_text()).get("model_type")
    if not model_type:
        raise EncoderError(f"encoder {name!r}: {folder / 'config.json'} has no model_type")
    return model_type


def _square(value: Any, where: str, key: str) -> int:
    if isinstance(value, int):
        return value
    if isinstance(value, dict):
        h, w = value.get("height", value.get("shortest_edge")), value.get("width", value.get("shortest_edge"))
        if isinstance(h, int) and h == w:
            return h
    raise EncoderError(f"{where}: {key}={value!r} is not a square size graftcache can use")
