#!/usr/bin/env python
"""LIBERO at its real size, measured here: a dataset of lerobot/libero's dimensions, extraction, sharding, the
streamed fit on a whole suite.

    python benchmarks/bench_scale.py [--work DIR] [--extract-episodes 12] [--encoder timm:test_vit]

1. `python -m devtools.tile --preset libero` from the bundled sample: 1,693 episodes, 273,465 frames, 2 cameras at
   256x256, each episode a window of the sample's AV1 frames (devtools/tile/). Time, files.
2. Extraction of the first `--extract-episodes` episodes with a cheap random-init encoder (the whole dataset is
   546,930 images: hours of any encoder on 2 cores): frames/s end to end and excluding the encoder (the
   encoder's bare forward time on as many images, measured in this process, subtracted from the extraction's
   decode+encode+write time: an estimate, the two overlap), bytes per frame (stored, and uncompressed), objects in
   the cache, and the object count of a whole-LIBERO cache of this encoder (same layout, 273,465 frames), peak RSS.
3. The same extraction as 2 processes `--shard 0/2` and `--shard 1/2` at once vs 1 process, and whether the two
   caches are byte-identical.
4. The streamed fit on a whole suite (`--suite`, default libero_spatial: 432 episodes, 52,970 frames): a cache of
   that suite laid out as `extract` writes it (the tiled dataset's own index, low-dim and action columns) with
   random fp16 features at the tiny SmolVLA's 4x4 grid, 768 wide (SigLIP-B's width): stream read throughput
   (frames/s of training batches drawn from the shuffle buffer, no model), and a `graftcache fit` of the tiny
   SmolVLA on it and on the bundled sample's suite with the same settings: wall time, steps/s, peak RSS, and the
   bytes the in-memory design would have loaded.
Everything runs on the CPU of this machine; the first line names it.
"""

from __future__ import annotations

import os

os.environ.setdefault("HF_HUB_OFFLINE", "1")

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import hashlib  # noqa: E402
import json  # noqa: E402
import shutil  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from contextlib import closing  # noqa: E402
from pathlib import Path  # noqa: E402

import torch  # noqa: E402
from common import DEFAULT_DATASET, machine  # noqa: E402

from devtools.tile import TileRequest, tile  # noqa: E402
from graftcache.datasets import open_dataset  # noqa: E402
from graftcache.encoders import load_encoder  # noqa: E402
from graftcache.fit.buffer import ShuffleBuffer, buffer_frames  # noqa: E402
from graftcache.fit.data import load_lowdim  # noqa: E402
from graftcache.fit.feed import SplitFeed  # noqa: E402
from graftcache.fit.stream import FeatureSource, read_blocks  # noqa: E402
from graftcache.requests import ExtractRequest  # noqa: E402
from graftcache.store import FeatureCache, list_caches  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from helpers.backbones import tiny  # noqa: E402
from helpers.caches import dataset_cache  # noqa: E402

LIBERO_FRAMES = 273_465
MIB = 2**20

#: One extraction in a fresh interpreter: its result and peak RSS (itself and its reaped decode workers), as JSON.
EXTRACT_PROBE = """
import json, resource, sys
from graftcache.extract import extract
from graftcache.requests import ExtractRequest
kw = {k: tuple(v) if isinstance(v, list) else v for k, v in json.loads(sys.argv[1]).items()}
res = extract(ExtractRequest(**kw), log=lambda _: None)
peak = max(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss, resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)
print(json.dumps({"encode_s": res.encode_s, "wall_s": res.wall_s, "n_frames": res.n_frames, "peak_kib": peak}))
"""


def run_child(args: list[str]) -> tuple[str, float, int]:
    """Run a child python process: (stdout, wall seconds, peak RSS in KiB of it and its reaped children)."""
    t0 = time.perf_counter()
    proc = subprocess.Popen([sys.executable, *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    _, status, usage = os.wait4(proc.pid, 0)
    out, err = proc.stdout.read(), proc.stderr.read()
    if os.waitstatus_to_exitcode(status) != 0:
        raise SystemExit(f"child failed: {' '.join(args[:4])} ...\n{err[-2000:]}")
    return out, time.perf_counter() - t0, usage.ru_maxrss


def extract_fields(dataset: Path, cache: Path, args: argparse.Namespace, **kw) -> dict:
    return {"dataset": str(dataset), "encoder": args.encoder, "random_init": True,
            "episodes": list(range(args.extract_episodes)), "num_workers": 2, "batch_size": 32,
            "compute_dtype": "fp32", "cache": str(cache), "progress": False, **kw}


def files_under(folder: Path) -> list[Path]:
    return [p for p in folder.rglob("*") if p.is_file()]


def section_tile(work: Path) -> Path:
    dest = work / "libero"
    if not dest.exists():
        t0 = time.perf_counter()
        tile(TileRequest(source=str(DEFAULT_DATASET), dest=str(dest), preset="libero"))
        print(f"tile: built in {time.perf_counter() - t0:.1f}s")
    meta = open_dataset(str(dest)).meta
    print(f"tile: {len(meta.episodes)} episodes, {meta.n_frames} frames, cameras {', '.join(meta.cameras)}, "
          f"{len(files_under(dest))} files ({sum(p.stat().st_size for p in files_under(dest)) / MIB:.1f} MiB, "
          f"videos linked)")
    return dest


def bare_encoder_seconds(name: str, images: int, batch: int = 32) -> float:
    """Seconds the encoder alone takes for `images` 256x256 frames (preprocess + forward), fp32, this process."""
    encoder = load_encoder(name, random_init=True)
    torch.set_num_threads(os.cpu_count() or 1)
    x = torch.randint(0, 256, (batch, 256, 256, 3), dtype=torch.uint8)
    with torch.inference_mode():
        encoder.forward_grid(encoder.preprocess(x))  # warm-up
        t0 = time.perf_counter()
        for _ in range(max(1, images // batch)):
            encoder.forward_grid(encoder.preprocess(x))
    return (time.perf_counter() - t0) * images / (max(1, images // batch) * batch)


def section_extract(dataset: Path, work: Path, args: argparse.Namespace) -> tuple[dict, FeatureCache]:
    cache_root = work / "extract-1"
    shutil.rmtree(cache_root, ignore_errors=True)
    out, wall, peak = run_child(["-c", EXTRACT_PROBE, json.dumps(extract_fields(dataset, cache_root, args))])
    res = json.loads(out.strip().splitlines()[-1])
    (cache,) = list_caches(cache_root)
    frames, cams = res["n_frames"], len(cache.manifest.cameras)
    enc_s = bare_encoder_seconds(args.encoder, frames * cams)
    folder = Path(cache.path)
    files = files_under(folder)
    stored = sum(p.stat().st_size for p in files)
    feature_files = [p for p in files if "features" in p.relative_to(folder).parts[:1] and p.name != "zarr.json"]
    per_frame_raw = sum(2 * int(torch.tensor(shape).prod()) for shape in cache.layout["arrays"].values())
    n_blocks_full = -(-LIBERO_FRAMES // int(cache.layout["block_frames"]))
    objects_full = len(files) - len(feature_files) + n_blocks_full * len(cache.layout["arrays"])
    print(f"extract ({args.encoder}, random-init, {args.extract_episodes} episodes, {frames} frames x {cams} "
          f"cameras, 2 decode workers): {frames / res['encode_s']:.1f} frames/s decode+encode+write, "
          f"{frames / wall:.1f} frames/s end to end (process start included); encoder alone {enc_s:.1f}s of "
          f"{res['encode_s']:.1f}s -> ~{frames / max(res['encode_s'] - enc_s, 1e-9):.0f} frames/s excluding the "
          f"encoder; peak RSS {peak / 1024:.0f} MiB")
    print(f"extract: {stored / frames / 1024:.1f} KiB stored per frame ({per_frame_raw / 1024:.1f} KiB uncompressed, "
          f"grid {cache.manifest.grids}); {len(files)} objects in this cache; a whole-LIBERO cache of this "
          f"encoder: {n_blocks_full} blocks -> {objects_full} objects, ~{stored / frames * LIBERO_FRAMES / 2**30:.1f} "
          f"GiB")
    return {"wall": wall, "encode_s": res["encode_s"]}, cache


def digest(folder: Path) -> dict[str, str]:
    """sha256 of every file under a cache folder except the group's zarr.json (times, command lines)."""
    return {p.relative_to(folder).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in files_under(folder) if p.relative_to(folder).as_posix() != "zarr.json"}


def section_shards(dataset: Path, work: Path, args: argparse.Namespace, single: dict, cache: FeatureCache) -> None:
    if "shard" not in {f.name for f in dataclasses.fields(ExtractRequest)}:
        print("shards: this graftcache has no sharded extraction")
        return
    root = work / "extract-2"
    shutil.rmtree(root, ignore_errors=True)
    t0 = time.perf_counter()
    procs = [subprocess.Popen([sys.executable, "-c", EXTRACT_PROBE,
                               json.dumps(extract_fields(dataset, root, args, shard=[i, 2]))],
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for i in range(2)]
    for p in procs:
        _, err = p.communicate()
        if p.returncode:
            raise SystemExit(f"shard failed:\n{err[-2000:]}")
    wall = time.perf_counter() - t0
    (sharded,) = list_caches(root)
    same = digest(Path(sharded.path)) == digest(Path(cache.path))
    print(f"shards: 2 processes at once {wall:.1f}s vs 1 process {single['wall']:.1f}s -> {single['wall'] / wall:.2f}x "
          f"(2 cores shared by both); complete {sharded.complete}; byte-identical to the 1-process cache: {same}")


def section_stream(dataset: Path, work: Path, args: argparse.Namespace) -> None:
    grid, width = (4, 4), 768
    policy = work / "tiny-smolvla"
    if not policy.exists():
        tiny("smolvla").save(policy)
    results = {}
    for name, source in (("sample", DEFAULT_DATASET), ("libero", dataset)):
        root = work / f"suite-{name}"
        caches = list_caches(root) if root.exists() else []
        cache = caches[0] if caches else dataset_cache(root, source, args.suite, grid=grid, width=width)
        cache = FeatureCache(cache.path, writable=False)
        if name == "libero":
            feed = SplitFeed(load_lowdim(cache, args.suite, chunk=50),
                             FeatureSource.of(cache, cache.manifest.cameras, grid),
                             int(cache.layout["block_frames"]))
            capacity = buffer_frames(args.buffer_mib, feed.source.frame_bytes(), 64, len(feed.low))
            g = torch.Generator().manual_seed(0)
            n = 64 * 200
            t0 = time.perf_counter()
            with closing(read_blocks(feed.features(seed=0), 2)) as blocks:
                buffer = ShuffleBuffer(blocks, capacity)
                for _ in range(n // 64):
                    buffer.draw(64, g)
            print(f"stream ({args.suite}, {cache.n_frames} frames, {grid[0]}x{grid[1]}x{width} fp16 x 2 cameras): "
                  f"{n / (time.perf_counter() - t0):.0f} frames/s of batches of 64 from a {capacity}-frame buffer "
                  f"({args.buffer_mib} MiB), 2 reading workers, first epoch (blocks checksum-checked)")
        fit = ["-m", "graftcache", "fit", "--backbone", "smolvla", "--policy", str(policy), "--encoder",
               cache.manifest.encoder_name, "--suite", args.suite, "--seed", "0", "--steps",
               str(args.fit_steps), "--batch-size", "32", "--buffer-mib", str(args.buffer_mib), "--num-workers", "2",
               "--eval-frames", "256", "--num-denoise-steps", "2", "--cache", str(root),
               "--results", str(work / f"results-{name}.parquet"), "--no-progress"]
        (work / f"results-{name}.parquet").unlink(missing_ok=True)
        _, wall, peak = run_child(fit)
        in_memory = cache.n_frames * FeatureSource.of(cache, cache.manifest.cameras, grid).frame_bytes()
        results[name] = peak
        print(f"fit ({name}: {cache.n_frames} frames of {args.suite}): {args.fit_steps} steps of 32 + 256 eval "
              f"frames in {wall:.1f}s ({args.fit_steps / wall:.2f} steps/s incl. start-up); peak RSS "
              f"{peak / 1024:.0f} MiB; the in-memory design would have loaded {in_memory / 2**30:.2f} GiB of features "
              f"(plus a copy for the split)")
    print(f"fit: peak RSS whole LIBERO-sized suite / sample suite = {results['libero'] / results['sample']:.2f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--work", type=Path, default=None, help="folder for the dataset and caches (default: a temp dir)")
    ap.add_argument("--extract-episodes", type=int, default=12)
    ap.add_argument("--encoder", default="timm:test_vit", help="a cheap encoder (random-init)")
    ap.add_argument("--suite", default="libero_spatial")
    ap.add_argument("--fit-steps", type=int, default=40)
    ap.add_argument("--buffer-mib", type=int, default=256)
    args = ap.parse_args()
    print(f"machine: {machine()}")
    with tempfile.TemporaryDirectory(prefix="bench_scale-") as tmp:
        work = args.work or Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        dataset = section_tile(work)
        single, cache = section_extract(dataset, work, args)
        section_shards(dataset, work, args, single, cache)
        section_stream(dataset, work, args)


if __name__ == "__main__":
    main()
