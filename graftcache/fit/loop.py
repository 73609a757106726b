"""The flow-matching training step, written once, and the scoring pass.

`fit` (projector, plus LoRA for that control) and `train-tiny` (the whole tiny policy, graftcache.pretrain)
both run `optimise`: draw a batch, the policy's own flow loss with padded steps masked, one optimiser
step. `train` and `evaluate` are the fit's use of it on a FrameTable of cached features.

Determinism: batch order, flow noise and flow time all come from one generator seeded by the caller
(the cell's seed), so a CPU rerun is bit-identical. Time is drawn like lerobot's `sample_time`
(Beta(1.5, 1) scaled to [0.001, 1]) by inverse-CDF sampling from that generator.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping

import numpy as np
import torch

from graftcache.fit.data import FrameTable
from graftcache.graft import feature_key
from graftcache.progress import progress
from graftcache.runtime import autocast
from graftcache.scoring import Score, frame_noise, predict_in_batches, score_chunks

EVAL_BATCH_SIZE = 64


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


def optimise(adapter, sample: Callable[[torch.Tensor], dict], n: int, *, steps: int, batch_size: int,
             optimizer: torch.optim.Optimizer, generator: torch.Generator, dtype: torch.dtype,
             scheduler: torch.optim.lr_scheduler.LRScheduler | None = None, clip_norm: float | None = None,
             desc: str = "fit", show: bool = True, leave: bool = True) -> list[float]:
    """`steps` flow-matching steps on the optimizer's parameters; returns the loss of every step.

    Each step draws `batch_size` of `n` rows from `generator`, makes the raw batch with `sample(rows)`,
    then noise and flow time from the same generator, in that order.
    """
    device = adapter.device
    params = [p for group in optimizer.param_groups for p in group["params"]]
    adapter.policy.train()
    losses: list[float] = []
    bar = progress(range(steps), desc=desc, unit="step", enabled=show, leave=leave)
    for _ in bar:
        pos = torch.randint(0, n, (batch_size,), generator=generator)
        batch = adapter.prepare(sample(pos))
        noise = adapter.sample_noise(batch_size, generator=generator)
        time = flow_time(batch_size, generator).to(device)
        with autocast(device, dtype):
            loss = adapter.loss(batch, noise=noise, time=time).mean()
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        if clip_norm is not None:
            torch.nn.utils.clip_grad_norm_(params, clip_norm)
        optimizer.step()
        if scheduler is not None:
            scheduler.step()
        losses.append(loss.item())
        bar.set_postfix(loss=f"{np.mean(losses[-20:]):.4f}")
    return losses


def train(adapter, table: FrameTable, cams: Mapping[str, str], *, steps: int, batch_size: int, lr: float,
          seed: int, dtype: torch.dtype = torch.float32, features: Mapping[str, torch.Tensor] | None = None,
          show: bool = True) -> float:
    """Optimise the trainable parameters (projector, LoRA) with AdamW; returns the mean loss of the last
    10% of steps (NaN when nothing is trainable)."""
    params = [p for p in adapter.policy.parameters() if p.requires_grad]
    if not params:
        return float("nan")
    losses = optimise(adapter, lambda pos: raw_batch(adapter, table, pos.numpy(), cams, features=features), len(table),
                      steps=steps, batch_size=batch_size, optimizer=torch.optim.AdamW(params, lr=lr, weight_decay=0.0),
                      generator=torch.Generator().manual_seed(seed), dtype=dtype, show=show, leave=False)
    return float(np.mean(losses[-max(1, len(losses) // 10):]))


@torch.no_grad()
def evaluate(adapter, table: FrameTable, cams: Mapping[str, str], *, dtype: torch.dtype = torch.float32,
             num_denoise_steps: int | None = None, features: Mapping[str, torch.Tensor] | None = None) -> Score:
    """Offline action MSE of the denoised chunk on every frame of `table` (fixed noise per frame)."""
    adapter.policy.eval()
    device = adapter.device
    noise = frame_noise(table.rows, adapter.chunk_size, adapter.max_action_dim)

    def predict(pos: np.ndarray, z: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        batch = adapter.prepare(raw_batch(adapter, table, pos, cams, features=features))
        with autocast(device, dtype):
            pred = adapter.predict(batch, noise=z, num_steps=num_denoise_steps)
        return batch["action"], pred

    target, pred = predict_in_batches(predict, table.rows, noise, EVAL_BATCH_SIZE)
    pred_raw = adapter.unnormalize(pred.to(device)).float().cpu()
    return score_chunks(pred, target.float(), pred_raw, table.actions, table.action_pad, table.episode_index)
