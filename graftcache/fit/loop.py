"""The flow-matching training step, written once, and the scoring pass.

`fit` (projector, plus LoRA for that control) and `train-tiny` (the whole tiny policy, graftcache.pretrain)
both run `optimise`: draw a batch, the policy's own flow loss with padded steps masked, one optimiser
step. `train` and `evaluate` are the fit's use of it on streamed cached features (graftcache.fit.stream):
`train` draws from a bounded shuffle buffer, `evaluate` scores the held-out frames chunk by chunk.

Determinism: batch draws, flow noise and flow time all come from one generator seeded by the caller
(the cell's seed), and the stream's chunk order from the same seed, so a CPU rerun is bit-identical. Time is drawn
like lerobot's `sample_time` (Beta(1.5, 1) scaled to [0.001, 1]) by inverse-CDF sampling from that generator.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping

import numpy as np
import torch

from graftcache.errors import FitError
from graftcache.fit.buffer import ShuffleBuffer
from graftcache.fit.controls import Transform, keep
from graftcache.fit.data import LowDim
from graftcache.fit.stream import Chunk, FrameQueue
from graftcache.graft import feature_key
from graftcache.progress import progress
from graftcache.runtime import autocast
from graftcache.scoring import Score, frame_noise, score_chunks

EVAL_BATCH_SIZE = 64


def raw_batch(low: LowDim, pos: np.ndarray, features: Mapping[str, torch.Tensor], cams: Mapping[str, str], *,
              actions: bool = True) -> dict:
    """A raw policy batch: `features` (camera -> [k, T, C], as streamed) under the policy cameras `cams` maps
    to them (graftcache.cameras.match_cameras), with the low-dim rows `pos` of `low` (raw state, the action
    chunks built here, task strings)."""
    idx = torch.from_numpy(pos)
    raw = {feature_key(key): features[cam].float() for key, cam in cams.items()}
    raw["observation.state"] = low.state[idx]
    raw["task"] = [low.tasks[int(t)] for t in low.task_index[idx]]
    if actions:
        raw["action"], raw["action_is_pad"] = low.action_chunks(pos)
    return raw


def flow_time(batch_size: int, generator: torch.Generator) -> torch.Tensor:
    """lerobot's time distribution: Beta(1.5, 1) * 0.999 + 0.001 (CDF t^1.5, inverted)."""
    u = torch.rand(batch_size, generator=generator)
    return u.pow(1.0 / 1.5) * 0.999 + 0.001


def optimise(adapter, draw: Callable[[torch.Generator], dict], *, steps: int, batch_size: int,
             optimizer: torch.optim.Optimizer, generator: torch.Generator, dtype: torch.dtype,
             scheduler: torch.optim.lr_scheduler.LRScheduler | None = None, clip_norm: float | None = None,
             desc: str = "fit", show: bool = True, leave: bool = True) -> list[float]:
    """`steps` flow-matching steps on the optimizer's parameters; returns the loss of every step.

    Each step draws a raw batch of `batch_size` with `draw(generator)`, then noise and flow time from the same
    generator, in that order.
    """
    device = adapter.device
    params = [p for group in optimizer.param_groups for p in group["params"]]
    adapter.policy.train()
    losses: list[float] = []
    bar = progress(range(steps), desc=desc, unit="step", enabled=show, leave=leave)
    for _ in bar:
        batch = adapter.prepare(draw(generator))
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


def train(adapter, low: LowDim, buffer: ShuffleBuffer, cams: Mapping[str, str], *, steps: int, batch_size: int,
          lr: float, seed: int, transform: Transform = keep, dtype: torch.dtype = torch.float32,
          show: bool = True) -> float:
    """Optimise the trainable parameters (projector, LoRA) with AdamW on batches drawn from `buffer` (its
    frames go with the low-dim rows of `low`); returns the mean loss of the last 10% of steps (NaN when
    nothing is trainable)."""
    params = [p for p in adapter.policy.parameters() if p.requires_grad]
    if not params:
        return float("nan")

    def draw(generator: torch.Generator) -> dict:
        owners, features = buffer.draw(batch_size, generator)
        return raw_batch(low, owners, transform(features), cams)

    losses = optimise(adapter, draw, steps=steps, batch_size=batch_size,
                      optimizer=torch.optim.AdamW(params, lr=lr, weight_decay=0.0),
                      generator=torch.Generator().manual_seed(seed), dtype=dtype, show=show, leave=False)
    return float(np.mean(losses[-max(1, len(losses) // 10):]))


@torch.no_grad()
def evaluate(adapter, low: LowDim, chunks: Iterator[Chunk], cams: Mapping[str, str], *, transform: Transform = keep,
             dtype: torch.dtype = torch.float32, num_denoise_steps: int | None = None) -> Score:
    """Offline action MSE of the denoised chunk on the frames of `low` that `chunks` deliver (in cache order,
    re-cut into batches of EVAL_BATCH_SIZE; fixed noise per frame); only predictions are kept."""
    adapter.policy.eval()
    device = adapter.device
    queue = FrameQueue(chunks)
    owners, targets, preds = [], [], []
    while (taken := queue.take(EVAL_BATCH_SIZE)) is not None:
        pos, (features,) = taken
        noise = frame_noise(low.rows[pos], adapter.chunk_size, adapter.max_action_dim)
        batch = adapter.prepare(raw_batch(low, pos, transform(features), cams))
        with autocast(device, dtype):
            pred = adapter.predict(batch, noise=noise, num_steps=num_denoise_steps)
        owners.append(pos)
        targets.append(batch["action"].float().cpu())
        preds.append(pred.float().cpu())
    if not owners:
        raise FitError("no held-out frame to score (every one was dropped)")
    order = np.argsort(np.concatenate(owners), kind="stable")  # frame order, whatever pairing fed them
    pos = np.concatenate(owners)[order]
    pred, target = torch.cat(preds)[torch.from_numpy(order)], torch.cat(targets)[torch.from_numpy(order)]
    pred_raw = adapter.unnormalize(pred.to(device)).float().cpu()
    actions, pad = low.action_chunks(pos)
    return score_chunks(pred, target, pred_raw, actions, pad, low.episode_index[pos], critical=low.critical_chunks(pos))
