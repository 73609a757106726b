#!/usr/bin/env python
"""What does the numerics check cost, per encoder registry family, on this machine?

    python benchmarks/bench_numerics.py [--repeats 5] [--real-size]

The check (graftcache.encoders.fingerprint.check_numerics) runs where a cache is resumed, fitted, shared
or verified: it rebuilds the cache's encoder from the manifest, runs the fixed probe batch under the
cache's compute dtype and compares sketches. Prints, per family, the median seconds of
- `probe`: the probe alone on a loaded encoder (what extraction adds to every cache),
- `check`: the whole check from a manifest (encoder load + probe + comparison),
for small members of each family (random-init timm ViT-Tiny, a 2-layer DINOv2 model folder via `hf:`,
the native towers of the tiny random-init policies) and the wheel family's real MobileNetV2; `--real-size`
adds random-init SigLIP B/16-256 (transformers) and ViT-S/16 (timm) at their released geometry.
Target: check < 1 s for every family.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path
from types import SimpleNamespace

import torch
from common import machine, median_seconds

from graftcache.backbones import load_backbone
from graftcache.backbones.tiny import TinyBuild
from graftcache.backbones.tower_encoder import native_name
from graftcache.encoders import load_encoder
from graftcache.encoders.fingerprint import check_numerics, fingerprint, library_versions
from graftcache.runtime import set_main_threads


def tiny_dinov2_folder(root: Path) -> Path:
    """A 2-layer DINOv2 saved as a transformers model folder with its image-processor recipe (`hf:<folder>`)."""
    import json

    import transformers

    folder = root / "tiny-dinov2"
    with torch.random.fork_rng():
        torch.manual_seed(0)
        config = transformers.Dinov2Config(hidden_size=64, num_hidden_layers=2, num_attention_heads=2,
                                           intermediate_size=128, patch_size=14, image_size=224)
        transformers.Dinov2Model(config).save_pretrained(folder)
    (folder / "preprocessor_config.json").write_text(json.dumps(
        {"size": {"height": 224, "width": 224}, "resample": 3, "do_normalize": True,
         "image_mean": [0.485, 0.456, 0.406], "image_std": [0.229, 0.224, 0.225]}))
    return folder


def tiny_policy(root: Path, backbone: str) -> Path:
    """A tiny random-init policy checkpoint folder (with unit normalisation stats) for a native tower."""
    tiny = TinyBuild()
    stats = {key: {name: torch.full((dim,), value) for name, value in
                   (("mean", 0.0), ("std", 1.0), ("min", -1.0), ("max", 1.0), ("q01", -1.0), ("q99", 1.0))}
             for key, dim in (("observation.state", tiny.state_dim), ("action", tiny.action_dim))}
    folder = root / f"policy-{backbone}"
    load_backbone(backbone, "tiny", dataset_stats=stats, tiny=tiny).save(folder)
    return folder


def members(root: Path, real_size: bool) -> list[tuple[str, str, dict]]:
    """(family, encoder name, load_encoder kwargs) per measured member."""
    out = [("timm", "timm:vit_tiny_patch16_224", {"random_init": True}),
           ("transformers", f"hf:{tiny_dinov2_folder(root)}", {}),
           ("wheel", "mobilenetv2", {}),
           ("native", native_name("smolvla"), {"policy": str(tiny_policy(root, "smolvla"))}),
           ("native", native_name("pi05"), {"policy": str(tiny_policy(root, "pi05"))})]
    if real_size:
        out += [("transformers", "siglip", {"random_init": True}),
                ("timm", "timm:vit_small_patch16_224", {"random_init": True})]
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--compute-dtype", default="fp32", choices=("fp32", "bf16"))
    ap.add_argument("--real-size", action="store_true")
    a = ap.parse_args()
    set_main_threads()
    print(machine())
    print(f"compute dtype {a.compute_dtype}, median of {a.repeats} (after one warm-up)")
    print(f"{'family':<13} {'encoder':<34} {'probe s':>8} {'check s':>8}  verdict")
    with tempfile.TemporaryDirectory() as tmp:
        for family, name, kwargs in members(Path(tmp), a.real_size):
            encoder = load_encoder(name, **kwargs)
            probe = median_seconds(lambda encoder=encoder: fingerprint(encoder, a.compute_dtype), a.repeats)
            manifest = SimpleNamespace(encoder_name=name, weights=encoder.weights_info,
                                       weights_sha256=encoder.weights_info["sha256"], versions=library_versions(),
                                       numerics=fingerprint(encoder, a.compute_dtype))
            cache = SimpleNamespace(key=name.rsplit("/", 1)[-1], manifest=manifest)  # all the check reads
            verdict = check_numerics(cache).status
            check = median_seconds(lambda cache=cache: check_numerics(cache), a.repeats)
            print(f"{family:<13} {name.rsplit('/', 1)[-1]:<34} {probe:8.3f} {check:8.3f}  {verdict}")


if __name__ == "__main__":
    main()
