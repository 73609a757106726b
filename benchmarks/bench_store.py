#!/usr/bin/env python
"""Cache roots: the fit data path's frames/s from a local root vs a loopback S3 server, and push/pull MB/s vs a
plain copy of the same objects.

    python benchmarks/bench_store.py [DATASET] [--width C] [--repeats N]

The cache holds the real index, low-dim columns and suites of DATASET (default data/libero_sample) and seeded
random fp16 features at SmolVLA's 8x8 grid for both cameras (width C, default 384): the store does not care what
encoder made the numbers, and extracting real ones would time the encoder. The S3 server is moto's (`moto_server`
in the venv) in its own process on 127.0.0.1, so client and server do not share a GIL.

Fit data path = one pass of a fit's feature stream over one suite (`graftcache.fit.stream`, read in this process:
features of both cameras, low-dim rows), every block checked against its checksum as stage 2 does. For S3: "cold"
starts from an empty local read-through copy, "warm" reuses it. Push/pull = `graftcache.store.push_pull.copy_cache`
(copy + verify at the destination + publish); the plain copy moves the same objects with the same 8 threads, no checks.
"""

from __future__ import annotations

import os

os.environ["OMP_NUM_THREADS"] = "1"
os.environ.setdefault("HF_HUB_OFFLINE", "1")

import argparse  # noqa: E402
import shutil  # noqa: E402
import socket  # noqa: E402
import statistics  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
import uuid  # noqa: E402
from concurrent.futures import ThreadPoolExecutor  # noqa: E402
from pathlib import Path  # noqa: E402

from common import DEFAULT_DATASET, machine  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from helpers.caches import dataset_cache  # noqa: E402

from graftcache.fit.data import load_lowdim  # noqa: E402
from graftcache.fit.feed import SplitFeed  # noqa: E402
from graftcache.fit.stream import FeatureSource, read_blocks  # noqa: E402
from graftcache.store import FeatureCache, open_root  # noqa: E402
from graftcache.store.push_pull import COPY_THREADS, copy_cache  # noqa: E402
from graftcache.store.readthrough import ReadThroughRoot  # noqa: E402
from graftcache.store.roots import Root  # noqa: E402

GRID, CHUNK, BLOCK = (8, 8), 50, 256


def make_cache(root: Path, dataset: str, width: int) -> tuple[str, list[str], list[str]]:
    """A cache of every episode of `dataset` at 8x8 x `width` (tests/helpers/caches.py's writer): its key, cameras
    and the suites its episodes are in."""
    cache = dataset_cache(root, dataset, None, grid=GRID, width=width, block_frames=BLOCK)
    suites = cache.manifest.suites
    present = sorted({suites[i] for i in cache.index()["suite_index"].unique().to_list()})
    return cache.key, list(cache.manifest.cameras), present


def frames_per_s(root: Root, key: str, cameras: list[str], suite: str, repeats: int) -> tuple[float, int]:
    """One pass of a fit's stream over the suite (every block checked, in this process), as frames/s."""
    times, n = [], 0
    for _ in range(repeats):
        t0 = time.perf_counter()
        cache = FeatureCache.in_root(root, key)  # a new handle: its blocks are checked again
        feed = SplitFeed(load_lowdim(cache, suite, chunk=CHUNK), FeatureSource.of(cache, cameras, GRID), BLOCK)
        n = sum(len(c.owners) for c in read_blocks(feed.features(seed=None), 0))
        times.append(time.perf_counter() - t0)
    return n / statistics.median(times), n


def plain_copy(src: Root, dst: Root, rels: list[str]) -> None:
    with ThreadPoolExecutor(COPY_THREADS) as threads:
        list(threads.map(lambda rel: dst.put(rel, src.get(rel)), rels))


def timed(fn) -> float:
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("dataset", nargs="?", default=str(DEFAULT_DATASET))
    ap.add_argument("--width", type=int, default=384)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    print(machine())
    print(subprocess.run(["lscpu"], capture_output=True, text=True).stdout.split("Model name:")[1].splitlines()[0]
          .strip() if shutil.which("lscpu") else "lscpu: absent")
    work = Path(tempfile.mkdtemp(prefix="bench_store-"))
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    server = subprocess.Popen([str(Path(sys.executable).with_name("moto_server")), "-H", "127.0.0.1", "-p", str(port)],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    os.environ.update(AWS_ENDPOINT_URL=f"http://127.0.0.1:{port}", AWS_ACCESS_KEY_ID="bench",
                      AWS_SECRET_ACCESS_KEY="bench", AWS_DEFAULT_REGION="us-east-1")
    try:
        import boto3

        bucket = f"bench-{uuid.uuid4().hex[:8]}"
        for _ in range(100):
            try:
                boto3.client("s3").create_bucket(Bucket=bucket)
                break
            except Exception:  # the server is still starting
                time.sleep(0.1)
        local = open_root(work / "local")
        key, cameras, suites = make_cache(work / "local", args.dataset, args.width)
        total = sum(local.sizes(f"{key}/").values())
        objects = sorted(local.sizes(f"{key}/"))
        print(f"cache: {FeatureCache.in_root(local, key).n_frames} frames, cameras {cameras}, 8x8 x {args.width} fp16, "
              f"{len(objects)} objects, {total / 2**20:.1f} MiB; suites {suites}")

        s3 = open_root(f"s3://{bucket}/push")
        push_s = timed(lambda: copy_cache(local, s3, key, log=lambda _: None))
        plain_up_s = timed(lambda: plain_copy(local, open_root(f"s3://{bucket}/plain"), objects))
        pull_s = timed(lambda: copy_cache(s3, open_root(work / "pulled"), key, log=lambda _: None))
        plain_down_s = timed(lambda: plain_copy(open_root(f"s3://{bucket}/plain"), open_root(work / "plain"),
                                                objects))
        local_copy_s = timed(lambda: shutil.copytree(work / "local" / key, work / "copytree" / key))
        mb = total / 1e6
        print(f"push  {mb / push_s:7.1f} MB/s  vs plain upload   {mb / plain_up_s:7.1f} MB/s  (ratio "
              f"{plain_up_s / push_s:.2f}; push = copy + verify every block at the destination + publish)")
        print(f"pull  {mb / pull_s:7.1f} MB/s  vs plain download {mb / plain_down_s:7.1f} MB/s  (ratio "
              f"{plain_down_s / pull_s:.2f}); local copytree {mb / local_copy_s:.1f} MB/s")

        for suite in suites:
            local_fps, n = frames_per_s(local, key, cameras, suite, args.repeats)
            cold, cold_bytes = [], []
            for _ in range(args.repeats):
                mirror = ReadThroughRoot(s3, Path(tempfile.mkdtemp(dir=work)))
                cold.append(frames_per_s(mirror, key, cameras, suite, 1)[0])
                cold_bytes.append(mirror.fetched_bytes)
            warm_fps, _ = frames_per_s(mirror, key, cameras, suite, args.repeats)
            cold_fps = statistics.median(cold)
            print(f"fit data path {suite} ({n} frames): local {local_fps:7.0f} frames/s | S3 cold {cold_fps:7.0f} "
                  f"frames/s (ratio {cold_fps / local_fps:.2f}), fetched {cold_bytes[0] / 2**20:.1f} of "
                  f"{total / 2**20:.1f} MiB | S3 warm {warm_fps:7.0f} frames/s (ratio {warm_fps / local_fps:.2f})")
    finally:
        server.terminate()
        server.wait()
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
