"""What one training step of a grafted policy holds in memory, measured on a small raw batch (graftcache/fit/
step_memory.py decides from it whether a fit's step fits; benchmarks/gpu_check.py checks it against real steps).

Two measures, both of a real forward of the policy's loss on the batch the caller built:
- `saved_bytes` (any device): the bytes autograd saves for the backward pass, each storage counted once. A lower
  bound: the backward's own peak, temporaries and what activation checkpointing keeps as layer inputs are not in
  it.
- `peak_step_bytes` (CUDA): the allocator's peak over a whole step, forward and backward, above what was allocated
  before it: everything the step holds at its worst moment, measured rather than modelled.
`frame_bytes` takes the one the device has on a 1- and a 2-frame batch: what one frame costs under the adapter's
recompute plan (graftcache.backbones.activation_checkpointing.PLANS).

Either leaves the policy's mode, the global RNG (CPU and device) and the trainable parameters' gradients as they
were, so the fit that follows computes what it would have computed without it.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator, Mapping

import torch

from graftcache.fit.loop import Route, alone, flow_time
from graftcache.runtime import autocast


@contextlib.contextmanager
def _probe(adapter) -> Iterator[None]:
    """The policy in the mode a measurement needs, its RNG and gradients restored after."""
    training = adapter.policy.training
    cuda = [adapter.device] if adapter.device.type == "cuda" else []
    trainable = [p for p in adapter.policy.parameters() if p.requires_grad]
    grads = [p.grad for p in trainable]
    for p in trainable:  # a backward here must not add into a gradient the fit holds
        p.grad = None
    with torch.random.fork_rng(devices=cuda):
        try:
            yield
        finally:
            adapter.policy.train(training)
            for p, g in zip(trainable, grads, strict=True):
                p.grad = g


def _loss(adapter, raw: Mapping, frames: int, dtype: torch.dtype, route: Route) -> torch.Tensor:
    generator = torch.Generator().manual_seed(0)
    batch = adapter.prepare(dict(raw))
    noise = adapter.sample_noise(frames, generator=generator)
    time = flow_time(frames, generator).to(adapter.device)
    with route([frames]), autocast(adapter.device, dtype):
        return adapter.loss(batch, noise=noise, time=time).mean()


def saved_bytes(adapter, raw: Mapping, frames: int, dtype: torch.dtype, route: Route = alone) -> int:
    """Bytes autograd keeps for backward after the loss of the `frames`-frame raw batch `raw`. Eval mode, no
    dropout masks: a lower bound; in training mode when the adapter checkpoints (lerobot checkpoints only in
    training mode), which counts what a training step saves, dropout masks included: still no more than the step
    holds."""
    storages: dict[int, int] = {}

    def pack(t: torch.Tensor) -> torch.Tensor:
        storage = t.untyped_storage()
        storages[storage.data_ptr()] = storage.nbytes()
        return t

    with _probe(adapter), torch.autograd.graph.saved_tensors_hooks(pack, lambda t: t):
        adapter.policy.train(adapter.recomputing)  # lerobot recomputes in training mode only
        _loss(adapter, raw, frames, dtype, route)
    return sum(storages.values())


def peak_step_bytes(adapter, raw: Mapping, frames: int, dtype: torch.dtype, route: Route = alone) -> int:
    """The CUDA allocator's peak over one training step (forward and backward, training mode, the adapter's
    activation checkpointing as set) of the `frames`-frame raw batch `raw`, above what was allocated before it."""
    device = adapter.device
    if device.type != "cuda":
        raise ValueError(f"peak_step_bytes measures a CUDA allocator, not {device}")
    torch.cuda.synchronize(device)
    before = torch.cuda.memory_allocated(device)
    torch.cuda.reset_peak_memory_stats(device)
    with _probe(adapter):
        adapter.policy.train()
        _loss(adapter, raw, frames, dtype, route).backward()
        torch.cuda.synchronize(device)
        peak = torch.cuda.max_memory_allocated(device)
    return peak - before


def frame_bytes(adapter, batch_of: Callable[[int], Mapping], dtype: torch.dtype,
                route: Route = alone) -> tuple[int, int]:
    """(what a 1-frame step holds, what each further frame adds) under the adapter's recompute plan as set, measured on
    `batch_of(1)` and `batch_of(2)` (raw batches): the CUDA allocator's peak on CUDA, autograd's saved bytes
    elsewhere."""
    measure = peak_step_bytes if adapter.device.type == "cuda" else saved_bytes
    two, one = (measure(adapter, batch_of(frames), frames, dtype, route) for frames in (2, 1))
    return one, max(0, two - one)
