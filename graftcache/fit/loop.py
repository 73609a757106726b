"""The flow-matching training step, written once, and the scoring pass.

`fit` (projector, plus LoRA for that control) and `train-tiny` (the whole tiny policy, graftcache.pretrain)
both run `optimise`: draw a batch, the policy's own flow loss with padded steps masked, one optimiser
step. `train` and `evaluate` are the fit's use of it on streamed cached features (graftcache.fit.stream):
`train` draws from a bounded shuffle buffer, `evaluate` scores the held-out frames block by block.
Both are written for several cells at once (`optimise_together`, `evaluate_together`: the cells of one backbone
pass, graftcache/fit/passes.py, their batches concatenated, each with its own loss, optimiser and random
stream); one cell is the case of one.

Determinism: batch draws, flow noise and flow time all come from one generator seeded by the caller
(the cell's seed), and the stream's block order from the same seed, so a CPU rerun is bit-identical. Time is drawn
like lerobot's `sample_time` (Beta(1.5, 1) scaled to [0.001, 1]) by inverse-CDF sampling from that generator.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import AbstractContextManager, nullcontext
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
import torch

from graftcache.errors import FitError
from graftcache.fit.dose import AS_IS, FrameTransform
from graftcache.graft import feature_key
from graftcache.progress import progress
from graftcache.runtime import autocast
from graftcache.scoring import Score, frame_noise, score_chunks

if TYPE_CHECKING:  # the step needs none of the data layer (polars, zarr): benchmarks/gpu_check.py runs without it
    from graftcache.fit.buffer import ShuffleBuffer
    from graftcache.fit.data import LowDim
    from graftcache.fit.stream import Block

#: Steps between the progress bar's loss readings (each one waits for the device).
POSTFIX_EVERY = 20


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


@dataclass
class Learner:
    """One cell's share of the training steps: its batches, the optimiser of its parameters (with its own
    schedule and gradient clipping) and its random stream (batch draws, flow noise, flow time)."""

    draw: Callable[[torch.Generator], dict]   # a raw batch of `batch_size` frames
    optimizer: torch.optim.Optimizer
    generator: torch.Generator
    scheduler: torch.optim.lr_scheduler.LRScheduler | None = None
    clip_norm: float | None = None
    _done: list[float] = field(default_factory=list, repr=False)
    _pending: list[torch.Tensor] = field(default_factory=list, repr=False)

    def record(self, loss: torch.Tensor) -> None:
        """Keep a step's loss on its device: reading it now (`.item()`) would make the host wait for the device
        at every step, so the next batch could not be prepared while the device computes this one."""
        self._pending.append(loss.detach())

    @property
    def losses(self) -> list[float]:
        """The loss of every step so far (one device sync for all the steps not read yet)."""
        if self._pending:
            self._done.extend(torch.stack(self._pending).float().cpu().tolist())
            self._pending.clear()
        return self._done

    @property
    def params(self) -> list[torch.nn.Parameter]:
        return [p for group in self.optimizer.param_groups for p in group["params"]]

    @property
    def final_loss(self) -> float:
        """Mean loss of the last 10% of steps."""
        return float(np.mean(self.losses[-max(1, len(self.losses) // 10):]))


#: Around each forward of several learners' rows: says which rows of the batch are whose (member i owns
#: sizes[i], in learner order), e.g. graftcache.graft.FusedProjector.rows.
Route = Callable[[Sequence[int]], AbstractContextManager]


def alone(sizes: Sequence[int]) -> AbstractContextManager:
    """The route of batches whose rows are all one cell's (one projector grafted): nothing to say."""
    return nullcontext()


def concat_raw(raws: Sequence[dict]) -> dict:
    """Raw batches (raw_batch's dicts) as one: tensors concatenated along the batch, task lists joined."""
    if len(raws) == 1:
        return raws[0]
    return {k: [x for r in raws for x in r[k]] if isinstance(v, list) else torch.cat([r[k] for r in raws])
            for k, v in raws[0].items()}


def optimise(adapter, draw: Callable[[torch.Generator], dict], *, steps: int, batch_size: int,
             optimizer: torch.optim.Optimizer, generator: torch.Generator, dtype: torch.dtype,
             scheduler: torch.optim.lr_scheduler.LRScheduler | None = None, clip_norm: float | None = None,
             desc: str = "fit", show: bool = True, leave: bool = True) -> list[float]:
    """`steps` flow-matching steps on the optimizer's parameters; returns the loss of every step.

    Each step draws a raw batch of `batch_size` with `draw(generator)`, then noise and flow time from the same
    generator, in that order.
    """
    learner = Learner(draw, optimizer, generator, scheduler, clip_norm)
    optimise_together(adapter, [learner], steps=steps, batch_size=batch_size, dtype=dtype, desc=desc, show=show,
                      leave=leave)
    return learner.losses


def optimise_together(adapter, learners: Sequence[Learner], *, steps: int, batch_size: int, dtype: torch.dtype,
                      route: Route = alone, desc: str = "fit", show: bool = True, leave: bool = True) -> None:
    """`steps` flow-matching steps of every learner in one forward and backward of the policy: their batches
    concatenated (learner order), each learner's loss the mean over its own rows, one backward of their sum
    (a learner's parameters see only its own loss: the policy treats samples independently), then each learner
    clips and steps on its own. Each learner's draws, noise and time come from its own generator in the order
    `optimise` takes them, so a learner trained with others computes what it computes alone, up to float
    rounding of the larger batch."""
    device = adapter.device
    adapter.policy.train()
    sizes = [batch_size] * len(learners)
    bar = progress(range(steps), desc=desc, unit="step", enabled=show, leave=leave)
    for step in bar:
        raws, noises, times = [], [], []
        for learner in learners:
            raws.append(learner.draw(learner.generator))
            noises.append(adapter.sample_noise(batch_size, generator=learner.generator))
            times.append(flow_time(batch_size, learner.generator))
        batch = adapter.prepare(concat_raw(raws))
        noise, time = torch.cat(noises), torch.cat(times).to(device)
        with route(sizes), autocast(device, dtype):
            loss = adapter.loss(batch, noise=noise, time=time)
        if loss.dim() == 0 and len(learners) > 1:  # Plan.pass_key keeps such backbones' cells alone
            raise FitError(f"{adapter.name}: its loss is one mean over the whole batch, so its cells cannot share a "
                           "backbone pass")
        losses = [loss] if loss.dim() == 0 else [part.mean() for part in loss.split(sizes)]
        for learner in learners:
            learner.optimizer.zero_grad(set_to_none=True)
        (losses[0] if len(losses) == 1 else torch.stack(losses).sum()).backward()
        for learner, loss in zip(learners, losses, strict=True):
            if learner.clip_norm is not None:
                torch.nn.utils.clip_grad_norm_(learner.params, learner.clip_norm)
            learner.optimizer.step()
            if learner.scheduler is not None:
                learner.scheduler.step()
            learner.record(loss)
        if show and (step % POSTFIX_EVERY == POSTFIX_EVERY - 1 or step == steps - 1):
            bar.set_postfix(loss=f"{np.mean([np.mean(x.losses[-POSTFIX_EVERY:]) for x in learners]):.4f}")


def learner(low: LowDim, buffer: ShuffleBuffer, cams: Mapping[str, str], params: Sequence[torch.nn.Parameter], *,
            batch_size: int, lr: float, seed: int, transform: FrameTransform = AS_IS) -> Learner:
    """A fit's learner: AdamW on `params`, batches drawn from `buffer` (its frames go with the low-dim rows of
    `low`; `transform` takes their cache rows), every random draw from a generator seeded with the cell's `seed`."""

    def draw(generator: torch.Generator) -> dict:
        owners, features = buffer.draw(batch_size, generator)
        return raw_batch(low, owners, transform(features, low.rows[owners]), cams)

    return Learner(draw, torch.optim.AdamW(params, lr=lr, weight_decay=0.0), torch.Generator().manual_seed(seed))


def train(adapter, low: LowDim, buffer: ShuffleBuffer, cams: Mapping[str, str], *, steps: int, batch_size: int,
          lr: float, seed: int, transform: FrameTransform = AS_IS, dtype: torch.dtype = torch.float32,
          show: bool = True) -> float:
    """Optimise the trainable parameters (projector, LoRA) with AdamW on batches drawn from `buffer` (its
    frames go with the low-dim rows of `low`); returns the mean loss of the last 10% of steps (NaN when
    nothing is trainable)."""
    params = [p for p in adapter.policy.parameters() if p.requires_grad]
    if not params:
        return float("nan")
    one = learner(low, buffer, cams, params, batch_size=batch_size, lr=lr, seed=seed, transform=transform)
    optimise_together(adapter, [one], steps=steps, batch_size=batch_size, dtype=dtype, show=show, leave=False)
    return one.final_loss


@dataclass
class Scoring:
    """One cell's share of an evaluation: its held-out rows, their features as streamed, how they are fed."""

    low: LowDim
    blocks: Iterator[Block]
    cams: Mapping[str, str]
    transform: FrameTransform = AS_IS  # takes the frames' cache rows


def evaluate(adapter, low: LowDim, blocks: Iterator[Block], cams: Mapping[str, str], *, batch_size: int,
             transform: FrameTransform = AS_IS, dtype: torch.dtype = torch.float32,
             num_denoise_steps: int | None = None) -> Score:
    """Offline action MSE of the denoised chunk on the frames of `low` that `blocks` deliver (in cache order,
    re-cut into batches of `batch_size`; fixed noise per frame); only predictions are kept.

    Each batch's prefix (images and prompt through the frozen LM) is computed once and its KV cache reused by
    every denoising step: lerobot's `sample_actions` does so (`predict` calls it), so a step costs only the
    action expert's pass over the chunk."""
    return evaluate_together(adapter, [Scoring(low, blocks, cams, transform)], batch_size=batch_size, dtype=dtype,
                             num_denoise_steps=num_denoise_steps)[0]


@torch.no_grad()
def evaluate_together(adapter, parts: Sequence[Scoring], *, batch_size: int, dtype: torch.dtype = torch.float32,
                      num_denoise_steps: int | None = None, route: Route = alone) -> list[Score]:
    """`evaluate` of several cells in one pass of the policy per batch: `batch_size` frames of each part
    (fewer once a part runs short, none once it has run out), concatenated in part order; each part's score from
    its own rows. `route` is told every part's rows, 0 for one that has run out: parts may hold out unequal numbers
    of frames (another --eval-frames, frames dropped for NaN/inf), and part i's rows are member i's."""
    from graftcache.fit.stream import FrameQueue  # here: the training step above must import without the data layer

    adapter.policy.eval()
    device = adapter.device
    queues = [FrameQueue(p.blocks) for p in parts]
    kept: list[tuple[list, list, list]] = [([], [], []) for _ in parts]  # owners, targets, predictions
    open_parts = list(range(len(parts)))
    while True:
        taken = [(i, queues[i].take(batch_size)) for i in open_parts]
        open_parts = [i for i, t in taken if t is not None]
        taken = [(i, t) for i, t in taken if t is not None]
        if not taken:
            break
        raws, noises, sizes = [], [], []
        for i, (pos, (features,)) in taken:
            part = parts[i]
            noises.append(frame_noise(part.low.rows[pos], adapter.chunk_size, adapter.max_action_dim))
            raws.append(raw_batch(part.low, pos, part.transform(features, part.low.rows[pos]), part.cams))
            sizes.append(len(pos))
        batch = adapter.prepare(concat_raw(raws))
        owned = dict(zip(open_parts, sizes, strict=True))
        with route([owned.get(i, 0) for i in range(len(parts))]), autocast(device, dtype):
            pred = adapter.predict(batch, noise=torch.cat(noises), num_steps=num_denoise_steps)
        for (i, (pos, _)), target, rows in zip(taken, batch["action"].float().cpu().split(sizes),
                                               pred.float().cpu().split(sizes), strict=True):
            owners, targets, preds = kept[i]
            owners.append(pos)
            targets.append(target)
            preds.append(rows)
    return [_score(adapter, part.low, *kept[i]) for i, part in enumerate(parts)]


def _score(adapter, low: LowDim, owners: list[np.ndarray], targets: list[torch.Tensor],
           preds: list[torch.Tensor]) -> Score:
    """A part's score from the batches it took part in."""
    if not owners:
        raise FitError("no held-out frame to score (every one was dropped)")
    order = np.argsort(np.concatenate(owners), kind="stable")  # frame order, whatever pairing fed them
    pos = np.concatenate(owners)[order]
    pred, target = torch.cat(preds)[torch.from_numpy(order)], torch.cat(targets)[torch.from_numpy(order)]
    pred_raw = adapter.unnormalize(pred.to(adapter.device)).float().cpu()
    actions, pad = low.action_chunks(pos)
    return score_chunks(pred, target, pred_raw, actions, pad, low.episode_index[pos], critical=low.critical_chunks(pos))
