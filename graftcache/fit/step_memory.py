"""What one training step of a fit holds in memory, measured before the first step, so a batch that cannot fit
(`fit --batch-size 100000`) is refused in one line instead of being killed by the kernel minutes later.

The estimate is three parts, all proportional to the batch: the shuffle buffer (at least one batch of stored
features, graftcache.fit.buffer.buffer_frames), the batch's features as the policy reads them (fp32), and the
activations the backward pass keeps. The last is measured, not modelled: one forward of the policy's loss on
a 1-frame and on a 2-frame batch, counting every tensor autograd saves (each storage once); the difference is
what a frame adds, whatever the backbone, its grid, width, LoRA or compute dtype. Weights saved for the
backward pass are in both and cancel. Peak use during backward is higher, so the estimate is a lower bound:
a refusal is never wrong.

The same measurement decides `--activation-checkpointing auto`: on only when the step measured without it would
not fit. Measured with it on, autograd saves only what lies outside the checkpointed layers (a layer's inputs are
held by the checkpoint, not saved), so that estimate is a lower bound too.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
import torch

from graftcache.budget import BudgetError, available_memory, require, size
from graftcache.fit.buffer import buffer_frames
from graftcache.fit.data import LowDim
from graftcache.fit.loop import Route, alone, flow_time, raw_batch
from graftcache.fit.stream import FeatureSource
from graftcache.runtime import autocast


def saved_bytes(adapter, low: LowDim, cams: Mapping[str, str], shapes: Mapping[str, tuple[int, int]],
                frames: int, dtype: torch.dtype, route: Route = alone) -> int:
    """Bytes autograd keeps for backward after the loss of a `frames`-frame batch (zero features, the first
    training frame's low-dim row), each storage counted once. Eval mode, no dropout masks: a lower bound; in
    training mode when the adapter checkpoints (lerobot checkpoints only in training mode), which counts what
    a training step saves, dropout masks included: still no more than the step holds."""
    storages: dict[int, int] = {}

    def pack(t: torch.Tensor) -> torch.Tensor:
        storage = t.untyped_storage()
        storages[storage.data_ptr()] = storage.nbytes()
        return t

    features = {cam: torch.zeros(frames, *shapes[cam]) for cam in set(cams.values())}
    generator = torch.Generator().manual_seed(0)
    training = adapter.policy.training
    cuda = [adapter.device] if adapter.device.type == "cuda" else []
    # the cell's seeded global RNG and the policy's mode are left as they were: the fit after it is unchanged
    with torch.random.fork_rng(devices=cuda), torch.autograd.graph.saved_tensors_hooks(pack, lambda t: t):
        adapter.policy.train(adapter.activation_checkpointing)
        try:
            batch = adapter.prepare(raw_batch(low, np.zeros(frames, dtype=np.int64), features, cams))
            noise = adapter.sample_noise(frames, generator=generator)
            time = flow_time(frames, generator).to(adapter.device)
            with route([frames]), autocast(adapter.device, dtype):
                adapter.loss(batch, noise=noise, time=time).mean()
        finally:
            adapter.policy.train(training)
    return sum(storages.values())


def check_step_memory(adapter, low: LowDim, cams: Mapping[str, str], source: FeatureSource, *,
                      batch_size: int, buffer_mib: int, dtype: torch.dtype, checkpointing: str = "off",
                      others: Sequence[tuple[LowDim, FeatureSource, int]] = (), route: Route = alone) -> bool:
    """Set the adapter's activation checkpointing as `checkpointing` says ("on", "off", or "auto": on only when
    the step measured without it would not fit) and return whether it is on; BudgetError (one line: the
    estimate, what a frame costs, the limit) when a step of `batch_size` cannot fit even so. `others`: the other
    cells of a backbone pass (graftcache/fit/passes.py), each (train rows, source, buffer MiB) with a shuffle
    buffer of its own and `batch_size` more frames in the step, fed tokens of the first cell's shapes; `route`
    gives the measuring batches' rows to the first cell's projector."""
    shapes = {cam: source.frame_shape(cam) for cam in set(cams.values())}
    adapter.set_activation_checkpointing(checkpointing == "on")
    try:
        _require_step(adapter, low, cams, source, shapes, batch_size, buffer_mib, dtype, others, route)
    except BudgetError:
        if checkpointing != "auto" or not adapter.can_checkpoint:
            raise
        adapter.set_activation_checkpointing(True)
        _require_step(adapter, low, cams, source, shapes, batch_size, buffer_mib, dtype, others, route)
    return adapter.activation_checkpointing


def _require_step(adapter, low: LowDim, cams: Mapping[str, str], source: FeatureSource,
                  shapes: Mapping[str, tuple[int, int]], batch_size: int, buffer_mib: int, dtype: torch.dtype,
                  others: Sequence[tuple[LowDim, FeatureSource, int]], route: Route) -> None:
    """BudgetError when a step of `batch_size` (per cell of the pass), measured as the adapter is set now, cannot
    fit."""
    two, one = (saved_bytes(adapter, low, cams, shapes, frames, dtype, route) for frames in (2, 1))
    per_frame = max(0, two - one)
    per_frame += sum(tokens * width * 4 for tokens, width in shapes.values())  # the batch's features in fp32
    held = sum(buffer_frames(mib, src.frame_bytes(), batch_size, len(rows)) * src.frame_bytes()
               for rows, src, mib in ((low, source, buffer_mib), *others))
    frames = batch_size * (1 + len(others))
    grid = ", ".join(f"{cam} {t}x{w}" for cam, (t, w) in sorted(shapes.items()))
    checkpointed = " with activation checkpointing" if adapter.activation_checkpointing else ""
    what = (f"a training step of --batch-size {batch_size}{checkpointed} ({size(per_frame)} a frame, measured on a "
            f"2-frame step of features {grid})")
    hint, buffers = "lower --batch-size", "shuffle buffer"
    if others:
        what = f"{what} for each of the {1 + len(others)} cells of a backbone pass"
        hint, buffers = "lower --cells-per-pass or --batch-size", "shuffle buffers"
    if not checkpointed:
        hint += " or pass --activation-checkpointing on"
    if adapter.device.type == "cuda":
        require(what, frames * per_frame, *available_memory(adapter.device), hint)
        require(f"the {buffers} ({size(held)}) of --batch-size {batch_size}", held,
                *available_memory("cpu"), hint + " or --buffer-mib")
    else:
        require(f"{what} with its {buffers} ({size(held)})", held + frames * per_frame,
                *available_memory("cpu"), hint)
