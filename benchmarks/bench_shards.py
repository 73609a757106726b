#!/usr/bin/env python
"""Is `extract --shard i/N` with N processes on one machine faster than one process, for the same cache?

    python benchmarks/bench_shards.py [--dataset DIR] [--encoder NAME] [--shards 2] [--episodes 0-11] [-- FLAGS]

Runs `graftcache extract` twice into fresh caches, each timed from launch to the last process's exit (startup,
encoder loading and finalising included, as a user waits for them): once as one process with every core, then
as N concurrent `--shard i/N` processes with cores/N torch threads each (OMP_NUM_THREADS, which
graftcache.runtime.set_main_threads honours). Prints both wall times, the speed-up (target: > 1 when the
per-process startup is small against the encoding), and checks that both runs made the same cache (same key,
same block checksums). `sharded_vs_single` is the function other benchmarks call (e.g. on a dataset built by
`python -m devtools.tile`).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from common import DEFAULT_DATASET, machine, warm_page_cache


@dataclass(frozen=True)
class ShardTiming:
    """Wall seconds of one process and of `shards` concurrent shard processes, for one cache key."""

    key: str
    shards: int
    single_s: float
    sharded_s: float

    @property
    def speedup(self) -> float:
        return self.single_s / self.sharded_s


def _run(flags: Sequence[str], cache: Path, shards: int) -> tuple[float, str]:
    """Wall time of `shards` concurrent extract processes (`--shard i/N` when shards > 1), and the key printed."""
    threads = max(1, (os.cpu_count() or 1) // shards)
    env = {**os.environ, "OMP_NUM_THREADS": str(threads)}
    base = [sys.executable, "-m", "graftcache", "extract", *flags, "--cache", str(cache), "--no-progress"]
    t0 = time.perf_counter()
    procs = [subprocess.Popen([*base, *(["--shard", f"{i}/{shards}"] if shards > 1 else [])], env=env,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for i in range(shards)]
    outs = [p.communicate() for p in procs]
    wall = time.perf_counter() - t0
    for p, (_, err) in zip(procs, outs):
        if p.returncode:
            raise SystemExit(f"extract failed ({p.returncode}): {err.strip().splitlines()[-1:]}")
    return wall, outs[0][0].strip().splitlines()[-1]


def _block_checksums(cache: Path) -> dict:
    attrs = json.loads((cache / "zarr.json").read_text())["attributes"]
    if not attrs.get("complete"):
        raise SystemExit(f"{cache}: not complete after every shard finished")
    return attrs["checksums"]


def sharded_vs_single(extract_flags: Sequence[str], shards: int = 2) -> ShardTiming:
    """Time `graftcache extract EXTRACT_FLAGS` as one process and as `shards` shard processes, each into a fresh
    cache in a temporary folder (removed afterwards); raises SystemExit if the two caches differ."""
    with tempfile.TemporaryDirectory(prefix="bench_shards_") as tmp:
        single_s, key = _run(extract_flags, Path(tmp) / "single", 1)
        sharded_s, sharded_key = _run(extract_flags, Path(tmp) / "sharded", shards)
        if sharded_key != key or _block_checksums(Path(tmp) / "single" / key) != _block_checksums(
                Path(tmp) / "sharded" / key):
            raise SystemExit(f"the sharded run made another cache ({sharded_key}) than the single run ({key})")
    return ShardTiming(key, shards, single_s, sharded_s)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--dataset", type=Path, default=DEFAULT_DATASET)
    p.add_argument("--encoder", default="mobilenetv2", help="registry name (default: real-weights MobileNetV2)")
    p.add_argument("--random-init", action="store_true")
    p.add_argument("--shards", type=int, default=2)
    p.add_argument("--episodes", default=None, help="episode subset, e.g. 0-11 (default: all)")
    p.add_argument("--num-workers", type=int, default=1, help="decode workers per process")
    p.add_argument("extra", nargs="*", help="more `graftcache extract` flags, after --")
    a = p.parse_args()

    warm_page_cache(a.dataset)
    flags = ["--dataset", str(a.dataset), "--encoder", a.encoder, "--num-workers", str(a.num_workers),
             *(["--random-init"] if a.random_init else []), *(["--episodes", a.episodes] if a.episodes else []),
             *a.extra]
    print(f"machine: {machine()}")
    print(f"extract {' '.join(flags)}")
    t = sharded_vs_single(flags, a.shards)
    cores = os.cpu_count() or 1
    print(f"one process ({cores} threads): {t.single_s:.1f}s; {t.shards} shard processes "
          f"({max(1, cores // t.shards)} thread(s) each): {t.sharded_s:.1f}s; speed-up {t.speedup:.2f}x "
          f"(same cache {t.key}, block checksums equal)")


if __name__ == "__main__":
    main()
