#!/usr/bin/env python
"""What the cache buys in stage 2: a `flow` step from cached features against an online graft step,
and an `align` cell against a `flow` cell.

    python benchmarks/bench_fit.py [--dataset DIR] [--encoder mobilenetv2] [--steps 300]

Prints, from one run on one machine (tiny SmolVLA at its real lerobot architecture, random init;
the step cost does not depend on what the weights learned):
- median step time of `flow` from the cache (batch of cached features -> prepare -> loss -> backward ->
  AdamW), and of the same step done online: decode each sample's frames with lerobot's
  `LeRobotDataset.__getitem__` (pyav, in process), run the encoder, pool, then the same step;
  ratio online / cached (target >= 5);
- per-cell cost with the CLI's defaults: `flow` (training + scoring) and `align` (ridge onto the
  native tower's tokens + the same scoring), their fit-only parts, and the ratios flow / align
  (target >= 100).
"""

from __future__ import annotations

import argparse
import tempfile
import time
from contextlib import closing
from pathlib import Path

import numpy as np
import torch
from common import DEFAULT_DATASET, machine, median_seconds, warm_page_cache

from graftcache.backbone_registry import native_name
from graftcache.backbones import load_backbone
from graftcache.cameras import match_cameras
from graftcache.encoders import load_encoder
from graftcache.extract import ExtractRequest, extract
from graftcache.fit.align import fit_ridge
from graftcache.fit.buffer import ShuffleBuffer
from graftcache.fit.data import load_lowdim
from graftcache.fit.feed import SplitFeed
from graftcache.fit.local import Fitter
from graftcache.fit.loop import flow_time, raw_batch, train
from graftcache.fit.run import FitRequest
from graftcache.fit.stream import FeatureSource, read_blocks
from graftcache.graft import GraftProjector, feature_key
from graftcache.pooling import pool_grid
from graftcache.pretrain import dataset_stats
from graftcache.runtime import autocast, resolve_compute_dtype, resolve_device, resolve_dtype, set_main_threads
from graftcache.store import FeatureCache

SUITE = "libero_spatial"


def _quiet(_: str) -> None:
    pass


def step_fn(adapter, opt, make_raw, batch_size: int, g: torch.Generator):
    """One optimiser step on a raw batch built by `make_raw(pos)` (cached or online features)."""
    def step() -> None:
        pos = torch.randint(0, 10**9, (batch_size,), generator=g).numpy()
        batch = adapter.prepare(make_raw(pos))
        loss = adapter.loss(batch, noise=adapter.sample_noise(batch_size, generator=g),
                            time=flow_time(batch_size, g)).mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if adapter.device.type == "cuda":  # the step's time, not its launch's
            torch.cuda.synchronize(adapter.device)
    return step


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--dataset", type=Path, default=DEFAULT_DATASET)
    p.add_argument("--encoder", default="mobilenetv2")
    p.add_argument("--random-init", action="store_true", help="random-init encoder weights (any registry family)")
    p.add_argument("--episodes", default="0-11", help="episodes to cache (libero_spatial ones in the sample)")
    p.add_argument("--batch-size", type=int, default=16)
    p.add_argument("--repeats", type=int, default=20)
    p.add_argument("--steps", type=int, default=300, help="flow steps per cell (the CLI default)")
    p.add_argument("--device", default="cpu", help="cpu, cuda or cuda:N (extraction, fits and steps run there)")
    p.add_argument("--compute-dtype", default="auto", choices=("auto", "bf16", "fp32"))
    a = p.parse_args()
    device = resolve_device(a.device)
    compute = resolve_compute_dtype(a.compute_dtype, device)

    set_main_threads()
    lo, hi = (int(v) for v in a.episodes.split("-"))
    episodes = tuple(range(lo, hi + 1))
    warm_page_cache(a.dataset)
    print(f"machine: {machine()}; device {device}, compute {compute}")
    with tempfile.TemporaryDirectory(prefix="bench_fit_") as tmp:
        root = Path(tmp)
        common = dict(dataset=str(a.dataset), episodes=episodes, num_workers=1, batch_size=32, compute_dtype=compute,
                      device=str(device),
                      cache=str(root / "cache"), progress=False)
        enc_key = extract(ExtractRequest(encoder=a.encoder, grids=("4x4",), random_init=a.random_init, **common),
                          log=_quiet).key
        cache = FeatureCache(root / "cache" / enc_key)
        stats = dataset_stats(cache.index())
        policy_dir = root / "policy"
        load_backbone("smolvla", "tiny", dataset_stats=stats).save(policy_dir)
        native_key = extract(ExtractRequest(encoder=native_name("smolvla"), grids=("4x4",), policy=str(policy_dir),
                                            **common), log=_quiet).key

        adapter = load_backbone("smolvla", policy_dir, device=str(device))
        cams = match_cameras(adapter.cameras, cache.manifest.cameras, None, policy_name=adapter.name,
                             cache_name=str(cache.path))
        low = load_lowdim(cache, SUITE, chunk=adapter.chunk_size)
        source = FeatureSource.of(cache, list(cams.values()), (4, 4))
        feats = source.read(low.rows)  # the sample's suite is small: the step timings read from memory
        width = source.frame_shape(source.cameras[0])[1]

        def cached_raw(pos: np.ndarray) -> dict:
            return raw_batch(low, pos, {c: f[torch.from_numpy(pos)] for c, f in feats.items()}, cams)

        adapter.graft(GraftProjector(width, adapter.lm_width))
        opt = torch.optim.AdamW([q for q in adapter.policy.parameters() if q.requires_grad], lr=1e-3)
        adapter.policy.train()
        g = torch.Generator().manual_seed(0)
        n = len(low)
        cached = median_seconds(step_fn(adapter, opt, lambda pos: cached_raw(pos % n),
                                        a.batch_size, g), a.repeats)
        print(f"flow step from the cache: {cached * 1e3:.0f} ms (batch {a.batch_size}, median of {a.repeats})")

        from lerobot.datasets.lerobot_dataset import LeRobotDataset

        online_ds = LeRobotDataset("local/bench", root=a.dataset, video_backend="pyav")
        encoder = load_encoder(a.encoder, random_init=a.random_init, device=device)
        dataset_rows = low.rows  # cache row == dataset index (the cache keeps dataset order)

        def online_raw(pos: np.ndarray) -> dict:
            items = [online_ds[int(dataset_rows[i % n])] for i in pos]
            raw = cached_raw(pos % n)
            for key, cam in cams.items():
                frames = torch.stack([(it[f"observation.images.{cam}"] * 255).round().to(torch.uint8) for it in items])
                with torch.inference_mode(), autocast(device, resolve_dtype(compute)):
                    grid = encoder.forward_grid(encoder.preprocess(frames.permute(0, 2, 3, 1)))
                raw[feature_key(key)] = pool_grid(grid.float(), (4, 4)).cpu().clone()
            return raw

        online = median_seconds(step_fn(adapter, opt, online_raw, a.batch_size, g), max(5, a.repeats // 4))
        print(f"online graft step (lerobot decode + {a.encoder} + same step): {online * 1e3:.0f} ms")
        print(f"ratio online / cached step: {online / cached:.1f}x (target >= 5)")

        results = root / "results.parquet"
        req = FitRequest(backbone="smolvla", encoder=a.encoder, suite=SUITE, policy=str(policy_dir),
                         cache_key=enc_key, seeds=(0,), steps=a.steps, batch_size=a.batch_size,
                         cache=str(root / "cache"), results=str(results), progress=False, command="bench_fit",
                         device=str(device), compute_dtype=compute)
        (flow_row,) = Fitter(req, log=_quiet).run()
        (align_row,) = Fitter(FitRequest(**{**req.__dict__, "objective": "align"}), log=_quiet).run()
        print(f"flow cell ({a.steps} steps + scoring {flow_row['n_eval_frames']} frames): {flow_row['wall_s']:.1f}s; "
              f"align cell (ridge + the same scoring): {align_row['wall_s']:.2f}s; "
              f"ratio {flow_row['wall_s'] / align_row['wall_s']:.0f}x")

        native = FeatureCache(root / "cache" / native_key)
        targets = FeatureSource.of(native, source.cameras, None, "connector").read(
            load_lowdim(native, SUITE, chunk=adapter.chunk_size).rows)
        feed = SplitFeed(low, source, cache.layout["block_frames"])
        t0 = time.perf_counter()
        with closing(read_blocks(feed.features(seed=0), 0)) as blocks:
            train(adapter, low, ShuffleBuffer(blocks, len(low)), cams, steps=a.steps, batch_size=a.batch_size,
                  lr=FitRequest.lr, seed=0, show=False)
        train_s = time.perf_counter() - t0
        projector = GraftProjector(width, adapter.lm_width)
        ridge_s = median_seconds(lambda: fit_ridge(projector, [(feats[c], targets[c]) for c in cams.values()],
                                                   (4, 4)), 5)
        print(f"fit only: flow training {train_s:.1f}s, ridge {ridge_s * 1e3:.0f} ms ({width}-wide features: the ridge "
              f"costs O(rows x width^2)); ratio {train_s / ridge_s:.0f}x (target >= 100)")


if __name__ == "__main__":
    main()
