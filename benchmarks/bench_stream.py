#!/usr/bin/env python
"""The fit's feature stream: random-batch read throughput against what a GPU fit step consumes, the read cost of
the stream's unit, and peak memory against the shuffle buffer's size.

    python benchmarks/bench_stream.py [--frames 2048] [--width 768] [--workers 1,2] [--batch-size 64]

Synthetic cache (the store does not care what encoder made the numbers): seeded random fp16 features of two
cameras at pi0.5's 16x16 grid, `--width` wide (768: SigLIP-B, pi0.5's and most candidates' width), blocks of 256
frames as `extract` writes them. Prints:
- frames/s of training batches (`--batch-size`) drawn from the shuffle buffer over the stream, for the 16x16 grid
  (pi0.5) and the 8x8 grid (SmolVLA) pooled from it in the workers (as read_grid pools a finer stored grid), per
  worker count, first epoch (every block checked against its checksum) and second epoch; against the frames/s a
  fit step consumes on a GPU. That figure is assumed, not measured here: lerobot documents SmolVLA training at
  ~0.5-0.7 s per step at batch 64 on one A100, i.e. <= ~128 frames/s; target >= 5x that. The 16x16 grid is
  also set against pi0.5's grafted step as measured on an H100 (bf16, features from a cache:
  benchmarks/results/bench_real_size_pi05_h100_bf16.json, written by bench_real_size.py), its largest batch;
- the read cost per frame of a whole block against runs of 32 rows inside a block (why the streamed
  unit is a whole block);
- peak RSS of a process streaming 200 batches, per `--buffer-mib` (the fit's memory flag), in a fresh
  subprocess each (ru_maxrss of the consumer; workers hold at most their prefetched blocks).
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from contextlib import closing
from pathlib import Path

import numpy as np
import torch
from common import machine

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from helpers.caches import synthetic_cache  # noqa: E402

from graftcache.fit.buffer import ShuffleBuffer, buffer_frames
from graftcache.fit.data import load_lowdim
from graftcache.fit.feed import SplitFeed
from graftcache.fit.stream import FeatureSource, read_blocks
from graftcache.store import FeatureCache

CAMERAS = ("image", "image2")
BLOCK = 256
GPU_FRAMES_PER_S = 128  # lerobot's SmolVLA figure: ~0.5 s per step of 64 frames on one A100 (assumed, see above)
PI05_MEASURED = Path(__file__).resolve().parent / "results" / "bench_real_size_pi05_h100_bf16.json"
EPISODE = 128  # frames per synthetic episode


def measured_pi05() -> tuple[float, str]:
    """(frames/s, what it is) of pi0.5's grafted training step on cached features at its largest measured batch."""
    record = json.loads(PI05_MEASURED.read_text())
    step = max((r for r in record["results"] if r["phase"] == "cached step"), key=lambda r: r["batch"])
    gpu = next((part for part in record["machine"].split("; ") if part.startswith("NVIDIA")), record["device"])
    return step["batch"] / step["seconds"], (f"pi0.5 grafted step measured on an {gpu} ({record['compute_dtype']}, "
                                             f"batch {step['batch']}: {step['seconds']:.3f} s)")


def make_cache(path: Path, frames: int, width: int) -> FeatureCache:
    """`frames` frames of EPISODE-frame episodes at 16x16 x `width` (tests/helpers/caches.py's writer)."""
    lengths = [EPISODE] * (frames // EPISODE) + ([frames % EPISODE] if frames % EPISODE else [])
    return synthetic_cache(path, lengths, grid=(16, 16), width=width, block_frames=BLOCK)


def feed_of(cache: FeatureCache, grid: tuple[int, int]) -> SplitFeed:
    return SplitFeed(load_lowdim(cache, "libero_spatial", chunk=50), FeatureSource.of(cache, CAMERAS, grid), BLOCK)


def batches_per_s(feed: SplitFeed, workers: int, batch: int, frames: int, mib: int) -> float:
    """Frames/s of `frames` frames of batches drawn from the buffer (its fill included)."""
    capacity = buffer_frames(mib, feed.source.frame_bytes(), batch, len(feed.low))
    g = torch.Generator().manual_seed(0)
    t0 = time.perf_counter()
    with closing(read_blocks(feed.features(seed=0), workers)) as blocks:
        buffer = ShuffleBuffer(blocks, capacity)
        for _ in range(frames // batch):
            buffer.draw(batch, g)
    return frames / (time.perf_counter() - t0)


def read_cost(cache: FeatureCache, run: int, repeats: int = 3) -> float:
    """Seconds per frame reading `run` consecutive rows of each block (blocks already checked)."""
    rows = np.concatenate([np.arange(b * BLOCK, b * BLOCK + run) for b in range(cache.layout["n_blocks"])])
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        for b in range(cache.layout["n_blocks"]):
            cache.read_features("image", "16x16", rows[b * run:(b + 1) * run])
        best = min(best, time.perf_counter() - t0)
    return best / len(rows)


RSS_CHILD = """
import resource, sys, torch
from contextlib import closing
sys.path.insert(0, {bench!r})
from bench_stream import feed_of
from graftcache.fit.buffer import ShuffleBuffer, buffer_frames
from graftcache.fit.stream import read_blocks
from graftcache.store import FeatureCache
feed = feed_of(FeatureCache({path!r}, writable=False), (16, 16))
capacity = buffer_frames({mib}, feed.source.frame_bytes(), 64, len(feed.low))
g = torch.Generator().manual_seed(0)
with closing(read_blocks(feed.features(seed=0), {workers})) as blocks:
    buffer = ShuffleBuffer(blocks, capacity)
    for _ in range(200):
        buffer.draw(64, g)
print(capacity, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)
"""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=2048, help="frames in the synthetic cache")
    ap.add_argument("--width", type=int, default=768)
    ap.add_argument("--workers", default="1,2")
    ap.add_argument("--batch-size", type=int, default=64)
    ap.add_argument("--buffer-mib", type=int, default=512, help="buffer of the throughput runs")
    ap.add_argument("--rss-mib", default="64,256,1024")
    a = ap.parse_args()
    print(f"machine: {machine()}")
    lscpu = subprocess.run(["lscpu"], capture_output=True, text=True, check=False).stdout.splitlines()
    print("lscpu: " + next((ln.split(":", 1)[1].strip() for ln in lscpu if ln.startswith("Model name")), "?"))
    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory(prefix="bench_stream_") as tmp:
        t0 = time.perf_counter()
        cache = make_cache(Path(tmp) / "bench", a.frames, a.width)
        mb = cache.size_bytes() / 2**20
        print(f"cache: {a.frames} frames x 2 cameras x 16x16 x {a.width} fp16 = "
              f"{a.frames * 2 * 256 * a.width * 2 / 2**20:.0f} MiB raw, {mb:.0f} MiB stored, "
              f"written in {time.perf_counter() - t0:.0f}s")
        target = 5 * GPU_FRAMES_PER_S
        pi05_rate, pi05_what = measured_pi05()
        for grid in ((16, 16), (8, 8)):
            for workers in (int(w) for w in a.workers.split(",")):
                feed = feed_of(cache, grid)  # a new reader: its first epoch checks every block again
                first = batches_per_s(feed, workers, a.batch_size, len(feed.low), a.buffer_mib)
                second = batches_per_s(feed, workers, a.batch_size, len(feed.low), a.buffer_mib)
                print(f"grid {grid[0]}x{grid[1]}, {workers} worker(s): {first:.0f} frames/s first epoch (checksums), "
                      f"{second:.0f} frames/s after; {min(first, second) / GPU_FRAMES_PER_S:.1f}x the assumed GPU "
                      f"step's {GPU_FRAMES_PER_S} frames/s (target >= 5x = {target})")
                if grid == (16, 16):
                    print(f"  {min(first, second) / pi05_rate:.1f}x the {pi05_what} = {pi05_rate:.0f} frames/s "
                          f"(target >= 5x = {5 * pi05_rate:.0f})")
        for run in (32, BLOCK):
            print(f"read cost, runs of {run} rows per block: {read_cost(cache, run) * 1e3:.2f} ms/frame (one camera)")
        bench = str(Path(__file__).resolve().parent)
        for mib in (int(m) for m in a.rss_mib.split(",")):
            code = RSS_CHILD.format(bench=bench, path=str(cache.path), mib=mib, workers=2)
            done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
            capacity, rss_kib = (int(v) for v in done.stdout.split()[-2:])
            children = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
            print(f"--buffer-mib {mib}: buffer {capacity} frames; peak RSS {rss_kib / 1024:.0f} MiB (largest "
                  f"process so far, workers included: {children / 1024:.0f} MiB)")


if __name__ == "__main__":
    main()
