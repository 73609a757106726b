#!/usr/bin/env python
"""Frames/s of graftcache's dataset reader vs lerobot's `LeRobotDataset.__getitem__` on the same dataset.

    python benchmarks/bench_reader.py [DATASET] [--workers N] [--lerobot-items M]

DATASET defaults to data/libero_sample when it exists; otherwise a synthetic LeRobot v3.0 video
dataset (256x256 AV1, 2 cameras, written by lerobot's own `LeRobotDataset.create`) is generated in a
temp dir. A "frame" is one camera image: the reader decodes every episode x every camera; lerobot's
item carries one image per camera, so its frames/s = items/s x cameras. Both sides run with
OMP_NUM_THREADS=1, sequentially and with N worker processes (torch DataLoader,
`runtime.single_thread_worker`). Lerobot is timed with each video backend it has (pyav, torchcodec)
and the faster one is the baseline.
"""

from __future__ import annotations

import os

os.environ["OMP_NUM_THREADS"] = "1"
os.environ.setdefault("HF_HUB_OFFLINE", "1")

import argparse  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable  # noqa: E402
from dataclasses import dataclass  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402
from common import DEFAULT_DATASET, machine, warm_page_cache  # noqa: E402
from torch.utils.data import DataLoader, Dataset  # noqa: E402

from devtools.scheduling import scheduling_kept  # noqa: E402
from graftcache.datasets import LeRobotSource, open_dataset  # noqa: E402
from graftcache.runtime import single_thread_worker  # noqa: E402


class Episodes(Dataset):
    """One item per episode: every camera's frames, decoded by the graftcache reader."""

    def __init__(self, src: LeRobotSource) -> None:
        self.src = src

    def __len__(self) -> int:
        return len(self.src.meta.episodes)

    def __getitem__(self, i: int) -> dict[str, np.ndarray]:
        return self.src.decode_episode(self.src.meta.episodes[i].index, self.src.meta.cameras)


def texture(rng: np.random.Generator, size: int, cell: int = 5) -> np.ndarray:
    """Smooth random RGB texture (blocky noise, box-blurred twice): LIBERO-like detail per pixel."""
    img = rng.integers(40, 220, (size // cell, size // cell, 3)).astype(np.float32).repeat(cell, 0).repeat(cell, 1)
    for _ in range(2):
        for axis in (0, 1):
            img = sum(np.roll(img, s, axis) for s in range(cell)) / cell
    return img.astype(np.uint8)


def synthesize(root: Path, episodes: int, length: int) -> Path:
    """A LIBERO-shaped v3.0 video dataset written by lerobot: 256x256 AV1, 2 cameras, fps 10, moving objects
    on a textured scene; the wrist camera pans. Encodes to ~4 KB/frame, like lerobot/libero."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    hwc = {"shape": (256, 256, 3), "names": ["height", "width", "channels"]}
    keys = ("observation.images.image", "observation.images.image2")
    features = {k: {"dtype": "video", **hwc} for k in keys}
    features["observation.state"] = {"dtype": "float32", "shape": (8,), "names": None}
    features["action"] = {"dtype": "float32", "shape": (7,), "names": None}
    ds = LeRobotDataset.create(repo_id="local/bench_synthetic", fps=10, features=features, root=root,
                               use_videos=True)
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:256, 0:256]
    with scheduling_kept():  # SVT-AV1 as root leaves this thread real-time (devtools/scheduling.py)
        for ep in range(episodes):
            scene = texture(rng, 320)
            for t in range(length):
                frame = {}
                for c, key in enumerate(keys):
                    dx = int(12 * np.sin(t / 15)) if c else 0
                    img = scene[20 + dx:276 + dx, 20:276].copy()
                    for k in range(3):
                        cx, cy = 60 + 1.2 * t + 50 * k, 100 + 40 * k + 20 * np.sin(t / 10 + k)
                        mask = (xx - cx) ** 2 + (yy - cy) ** 2 < 300 + 100 * k
                        img[mask] = scene[:256, :256][mask] // 2 + np.array([120, 40 * k, 30], np.uint8)
                    frame[key] = img
                ds.add_frame({**frame, "observation.state": rng.standard_normal(8).astype(np.float32),
                              "action": rng.uniform(-1, 1, 7).astype(np.float32), "task": f"synthetic task {ep % 3}"})
            ds.save_episode()
        ds.finalize()
    return root


@dataclass(frozen=True)
class Rate:
    """One timed configuration: camera frames, wall seconds and (in-process runs) CPU seconds."""

    frames: int
    wall: float
    cpu: float | None

    def __str__(self) -> str:
        cpu = f", {self.frames / self.cpu:.0f} frames/CPU-s" if self.cpu else ""
        return f"{self.frames} frames in {self.wall:.2f}s = {self.frames / self.wall:.0f} frames/s{cpu}"

    @property
    def fps(self) -> float:
        return self.frames / self.wall


def timed(run: Callable[[], int], in_process: bool) -> Rate:
    c0, t0 = time.process_time(), time.perf_counter()
    n = run()
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    return Rate(n, wall, cpu if in_process else None)


def time_reader(src: LeRobotSource, workers: int) -> Rate:
    """Every episode x camera, in-process or through a DataLoader with `workers` processes."""
    if workers == 0:
        return timed(lambda: sum(f.shape[0] for ep in Episodes(src) for f in ep.values()), True)
    loader = DataLoader(Episodes(src), batch_size=None, num_workers=workers, worker_init_fn=single_thread_worker)
    return timed(lambda: sum(f.shape[0] for ep in loader for f in ep.values()), False)


def time_lerobot(root: Path, backend: str | None, items: int, workers: int, cams: int) -> Rate:
    """`items` consecutive `__getitem__` calls (one image per camera each)."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    ds = LeRobotDataset("local/bench", root=root, video_backend=backend)
    idx = list(range(min(items, len(ds))))
    if workers == 0:
        ds[idx[-1]]  # lazy setup (decoder caches) is not part of the rate
        return timed(lambda: sum(cams for i in idx if ds[i]), True)
    loader = DataLoader(torch.utils.data.Subset(ds, idx), batch_size=None, num_workers=workers,
                        worker_init_fn=single_thread_worker)
    return timed(lambda: sum(cams for _ in loader), False)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("dataset", nargs="?", type=Path)
    p.add_argument("--workers", type=int, default=min(4, os.cpu_count() or 1))
    p.add_argument("--lerobot-items", type=int, default=400, help="items timed per lerobot configuration")
    p.add_argument("--synthetic-episodes", type=int, default=8)
    p.add_argument("--synthetic-length", type=int, default=150)
    a = p.parse_args()

    tmp = None
    root = a.dataset or (DEFAULT_DATASET if (DEFAULT_DATASET / "meta" / "info.json").is_file() else None)
    if root is None:
        tmp = tempfile.TemporaryDirectory(prefix="bench_reader_")
        t0 = time.perf_counter()
        root = synthesize(Path(tmp.name) / "ds", a.synthetic_episodes, a.synthetic_length)
        print(f"synthesized {root} in {time.perf_counter() - t0:.0f}s (data/libero_sample not found)")
    src = open_dataset(root, decode_threads=1)
    m = src.meta
    cams = len(m.cameras)
    print(f"machine: {machine()}")
    print(f"dataset: {root} ({m.codebase_version}, {len(m.episodes)} episodes, {m.n_frames} frames, cameras "
          f"{', '.join(f'{c}={m.camera_storage[c]} {m.image_shape[c][0]}x{m.image_shape[c][1]}' for c in m.cameras)})")
    warm_page_cache(root)

    print(f"load average before: {os.getloadavg()[0]:.2f}")
    reader = {w: time_reader(src, w) for w in (0, a.workers)}
    for w, r in reader.items():
        print(f"graftcache reader, {w or 'no'} workers: {r}")
    # lerobot's torchcodec decoders live in a module-level cache that forked workers must not inherit,
    # so worker runs go first
    backends = ["pyav", "torchcodec"] if "video" in m.camera_storage.values() else [None]
    lerobot: dict[str, dict[int, Rate]] = {}
    for backend in backends:
        for w in (a.workers, 0):
            try:
                r = time_lerobot(root, backend, a.lerobot_items, w, cams)
            except Exception as e:  # noqa: BLE001  (a backend lerobot cannot use here is reported, not fatal)
                print(f"LeRobotDataset backend={backend}, {w} workers: failed: {str(e).splitlines()[-1][:200]}")
                continue
            lerobot.setdefault(str(backend), {})[w] = r
            print(f"LeRobotDataset.__getitem__ backend={backend}, {w or 'no'} workers: {r}")
    print(f"load average after: {os.getloadavg()[0]:.2f}")

    parts, met = [], []
    for backend, rates in lerobot.items():
        ratios = {w: reader[w].fps / r.fps for w, r in rates.items()}
        parts.append(f"vs {backend}: " + ", ".join(f"{x:.1f}x {'sequential' if w == 0 else f'{w} workers'}"
                                                    for w, x in sorted(ratios.items())))
        met.append(f"{'met' if min(ratios.values()) >= 5 else 'NOT met'} vs {backend}")
    print(f"SUMMARY reader / LeRobotDataset.__getitem__ frames/s: {'; '.join(parts)} | target >= 5x: {', '.join(met)}"
          f" | reader {reader[0].fps:.0f} frames/s sequential, {reader[a.workers].fps:.0f} with {a.workers} workers")
    if tmp is not None:
        tmp.cleanup()


if __name__ == "__main__":
    main()
