"""The `flow` objective: train only the projector (and LoRA, for that control) with the policy's
own flow-matching loss, then score the denoised chunks of held-out frames.

Determinism: projector init, batch order, flow noise and flow time all come from generators
seeded by the cell's seed, so a CPU rerun is bit-identical. Time is drawn like lerobot's
`sample_time` (Beta(1.5, 1) scaled to [0.001, 1]) by inverse-CDF sampling from our generator.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass

import numpy as np
import torch

from graftcache.fit.data import FrameTable
from graftcache.graft import feature_key
from graftcache.progress import progress
from graftcache.runtime import autocast
from graftcache.scoring import Score, frame_noise, predict_in_batches, score_chunks


@dataclass(frozen=True)
class TrainConfig:
    steps: int = 300
    lr: float = 1e-3
    batch_size: int = 16
    weight_decay: float = 0.0
    eval_batch_size: int = 64
    num_denoise_steps: int | None = None
    dtype: torch.dtype = torch.float32
    progress: bool = True


def camera_map(adapter, cache_cameras: list[str]) -> dict[str, str]:
    """Policy camera key -> cache camera: by name when the cache has it, else by position."""
    out = {}
    for i, key in enumerate(adapter.camera_keys):
        short = key.removeprefix("observation.images.")
        if short in cache_cameras:
            out[key] = short
        elif i < len(cache_cameras):
            out[key] = cache_cameras[i]
    return out


def raw_batch(adapter, table: FrameTable, pos: np.ndarray, cams: Mapping[str, str], *,
              features: Mapping[str, torch.Tensor] | None = None, actions: bool = True) -> dict:
    """Rows `pos` of `table` as a raw policy batch (cached features, raw state/actions, task strings)."""
    feats = features if features is not None else table.features
    idx = torch.from_numpy(pos)
    raw = {feature_key(key): feats[cam][idx].float() for key, cam in cams.items()}
    raw["observation.state"] = table.state[idx]
    raw["task"] = [table.tasks[int(t)] for t in table.task_index[idx]]
    if actions:
        raw["action"] = table.actions[idx]
        raw["action_is_pad"] = table.action_pad[idx]
    return raw


def flow_time(batch_size: int, generator: torch.Generator) -> torch.Tensor:
    """lerobot's time distribution: Beta(1.5, 1) * 0.999 + 0.001 (CDF t^1.5, inverted)."""
    u = torch.rand(batch_size, generator=generator)
    return u.pow(1.0 / 1.5) * 0.999 + 0.001


def train(adapter, table: FrameTable, cams: Mapping[str, str], cfg: TrainConfig, seed: int,
          features: Mapping[str, torch.Tensor] | None = None,
          log: Callable[[str], None] = print) -> float:
    """Optimise the trainable parameters (projector, LoRA) for `cfg.steps`; returns the mean loss
    of the last 10% of steps."""
    params = [p for p in adapter.policy.parameters() if p.requires_grad]
    if not params or cfg.steps == 0:
        return float("nan")
    opt = torch.optim.AdamW(params, lr=cfg.lr, weight_decay=cfg.weight_decay)
    g = torch.Generator().manual_seed(seed)
    device = adapter.device
    adapter.policy.train()
    losses = []
    bar = progress(range(cfg.steps), desc="fit", unit="step", enabled=cfg.progress, leave=False)
    for _ in bar:
        pos = torch.randint(0, len(table), (cfg.batch_size,), generator=g).numpy()
        batch = adapter.prepare(raw_batch(adapter, table, pos, cams, features=features))
        noise = adapter.sample_noise(cfg.batch_size, generator=g)
        time = flow_time(cfg.batch_size, g).to(device)
        with autocast(device, cfg.dtype):
            loss = adapter.loss(batch, noise=noise, time=time).mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        losses.append(loss.item())
        bar.set_postfix(loss=f"{losses[-1]:.4f}")
    tail = losses[-max(1, len(losses) // 10):]
    return float(np.mean(tail))


@torch.no_grad()
def evaluate(adapter, table: FrameTable, cams: Mapping[str, str], cfg: TrainConfig,
             features: Mapping[str, torch.Tensor] | None = None) -> Score:
    """Offline action MSE of the denoised chunk on every frame of `table` (fixed noise per frame)."""
    adapter.policy.eval()
    device = adapter.device
    noise = frame_noise(table.rows, adapter.chunk_size, adapter.max_action_dim)

    def predict(pos: np.ndarray, z: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        batch = adapter.prepare(raw_batch(adapter, table, pos, cams, features=features))
        with autocast(device, cfg.dtype):
            pred = adapter.predict(batch, noise=z, num_steps=cfg.num_denoise_steps)
        return batch["action"], pred

    target, pred = predict_in_batches(predict, table.rows, noise, cfg.eval_batch_size)
    pad = table.action_pad
    target_raw = table.actions
    pred_raw = adapter.unnormalize(pred.to(device)).float().cpu()
    return score_chunks(pred, target.float(), pred_raw, target_raw, pad, table.episode_index)
