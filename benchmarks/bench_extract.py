#!/usr/bin/env python
"""Does extraction hide decoding, preprocessing, pooling and writing behind the encoder? And does its
memory stay flat as the dataset grows?

    python benchmarks/bench_extract.py [--dataset DIR] [--encoder NAME] [--compute-dtype bf16]

Prints, from one run on one machine:
- the encoder's bare forward throughput (images/s): preprocessed tensors already in memory, the same
  batch size and compute dtype, median over repeated batches;
- `graftcache extract` into a fresh cache (images/s = frames x cameras / time), both for its
  decode+encode+write loop and end to end (startup and finalising included), and the ratios
  extract / bare (target >= 0.9);
- peak RSS (the extract process and its decode workers) for 1x and 4x the frames (a quarter of the
  episodes, then all), each in a fresh process and cache: it must not grow with dataset length.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import torch
from common import DEFAULT_DATASET, machine, median_seconds, warm_page_cache

from graftcache.datasets import open_dataset
from graftcache.encoders import load_encoder
from graftcache.extract import ExtractRequest, extract
from graftcache.runtime import autocast, resolve_dtype, set_main_threads

#: Runs one extract in a fresh interpreter and reports its peak RSS (self + decode workers), in MiB.
RSS_PROBE = """
import json, resource, sys
from graftcache.extract import ExtractRequest, extract
req = ExtractRequest(**json.loads(sys.argv[1]))
extract(req, log=lambda _: None)
peak = max(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss, resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)
print(json.dumps({"peak_mib": peak / 1024}))
"""


def bare_forward(encoder_name: str, random_init: bool, size: tuple[int, int], batch: int, compute: str,
                 repeats: int) -> float:
    """Images/s of preprocess-free encoder forward on in-memory batches."""
    enc = load_encoder(encoder_name, random_init=random_init)
    frames = torch.randint(0, 256, (batch, *size, 3), dtype=torch.uint8)
    x = enc.preprocess(frames)
    dev = torch.device("cpu")

    def step() -> None:
        with torch.inference_mode(), autocast(dev, resolve_dtype(compute)):
            enc.forward_grid(x)

    return batch / median_seconds(step, repeats)


def peak_rss(request: dict) -> float:
    out = subprocess.run([sys.executable, "-c", RSS_PROBE, json.dumps(request)], capture_output=True, text=True,
                         check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])["peak_mib"]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--dataset", type=Path, default=DEFAULT_DATASET)
    p.add_argument("--encoder", default="mobilenetv2", help="registry name (default: real-weights MobileNetV2)")
    p.add_argument("--random-init", action="store_true")
    p.add_argument("--batch-size", type=int, default=32)
    p.add_argument("--compute-dtype", default="bf16", choices=("fp32", "bf16"))
    p.add_argument("--num-workers", type=int, default=1)
    p.add_argument("--repeats", type=int, default=10)
    a = p.parse_args()

    set_main_threads()
    src = open_dataset(a.dataset)
    meta = src.meta
    warm_page_cache(meta.root)
    print(f"machine: {machine()}")
    print(f"dataset: {meta.root} ({meta.n_frames} frames x {len(meta.cameras)} cameras, "
          f"{len(meta.episodes)} episodes)")
    h, w, _ = meta.image_shape[meta.cameras[0]]
    bare = bare_forward(a.encoder, a.random_init, (h, w), a.batch_size, a.compute_dtype, a.repeats)
    print(f"bare forward: {bare:.1f} images/s ({a.encoder}, batch {a.batch_size}, {a.compute_dtype}, median of "
          f"{a.repeats} batches)")

    common = dict(dataset=str(meta.root), encoder=a.encoder, random_init=a.random_init, grids=("8x8", "4x4"),
                  batch_size=a.batch_size, compute_dtype=a.compute_dtype, num_workers=a.num_workers, progress=False)
    with tempfile.TemporaryDirectory(prefix="bench_extract_") as tmp:
        result = extract(ExtractRequest(**common, cache=f"{tmp}/full"), log=lambda _: None)
        images = result.n_frames * len(meta.cameras)
        rate, steady = images / result.wall_s, images / result.encode_s
        print(f"extract end to end: {rate:.1f} images/s ({images} images in {result.wall_s:.1f}s, startup and "
              f"finalising included); decode+encode+write alone: {steady:.1f} images/s in {result.encode_s:.1f}s, "
              f"{a.num_workers} decode worker(s)")
        print(f"ratio extract / bare forward: {steady / bare:.2f} steady state, {rate / bare:.2f} end to end "
              f"(target >= 0.9)")

        episodes = [e.index for e in meta.episodes]
        quarter = episodes[: max(1, len(episodes) // 4)]
        small = peak_rss({**common, "episodes": quarter, "cache": f"{tmp}/rss1"})
        large = peak_rss({**common, "cache": f"{tmp}/rss4"})
        n_small = sum(e.length for e in meta.episodes if e.index in set(quarter))
        print(f"peak RSS: {small:.0f} MiB for {n_small} frames (1x), {large:.0f} MiB for {meta.n_frames} frames "
              f"({meta.n_frames / n_small:.1f}x); ratio {large / small:.2f} (target: ~1, flat in dataset length)")


if __name__ == "__main__":
    main()
