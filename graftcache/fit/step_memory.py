"""What one training step of a fit holds in memory, measured before the first step, so a batch that cannot fit
(`fit --batch-size 100000`) is refused in one line instead of being killed by the kernel or the CUDA allocator
minutes later.

The step is measured, not modelled (graftcache/fit/step_bytes.py): a real step of the policy's loss on a 1-frame
and on a 2-frame batch; the difference is what a frame adds, whatever the backbone, its grid, width, LoRA or
compute dtype.
- On CUDA, the allocator's peak over the whole step (forward and backward): a step of B frames needs the 1-frame
  step's peak plus B - 1 frames more. Backward peaks, temporaries and checkpoint-held layer inputs are all in it.
- Elsewhere, the bytes autograd saves for the backward pass (each storage once) plus the batch's features in fp32
  and the shuffle buffer (at least one batch of stored features, graftcache.fit.buffer.buffer_frames): a lower
  bound, since the backward's own peak is higher, so a refusal is never wrong.

The same measurement decides `--recompute auto`: the backbone's recompute plans are measured in order of recompute
(graftcache.backbones.activation_checkpointing.PLANS: off, mlp, on) and the first whose step fits is the one the fit
runs; each plan's per-frame bytes are measured under it, not derived.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
import torch

from graftcache.backbones.activation_checkpointing import PLANS
from graftcache.budget import BudgetError, available_memory, require, size
from graftcache.fit.buffer import buffer_frames
from graftcache.fit.data import LowDim
from graftcache.fit.loop import Route, alone, raw_batch
from graftcache.fit.step_bytes import frame_bytes
from graftcache.fit.stream import FeatureSource


def _measuring_batch(low: LowDim, cams: Mapping[str, str], shapes: Mapping[str, tuple[int, int]],
                     frames: int) -> dict:
    """A `frames`-frame raw batch of zero features and the first training frame's low-dim row."""
    features = {cam: torch.zeros(frames, *shapes[cam]) for cam in set(cams.values())}
    return raw_batch(low, np.zeros(frames, dtype=np.int64), features, cams)


def check_step_memory(adapter, low: LowDim, cams: Mapping[str, str], source: FeatureSource, *,
                      batch_size: int, buffer_mib: int, dtype: torch.dtype, recompute: str = "off",
                      others: Sequence[tuple[LowDim, FeatureSource, int]] = (), route: Route = alone) -> str:
    """Put the adapter under the recompute plan `recompute` names (`--recompute`: a plan, or "auto": the first of the
    backbone's plans, least recompute first, whose step fits) and return it; BudgetError (one line: the estimate,
    what a frame costs, the limit) when a step of `batch_size` cannot fit even so. `others`: the other
    cells of a backbone pass (graftcache/fit/passes.py), each (train rows, source, buffer MiB) with a shuffle
    buffer of its own and `batch_size` more frames in the step, fed tokens of the first cell's shapes; `route`
    gives the measuring batches' rows to the first cell's projector."""
    shapes = {cam: source.frame_shape(cam) for cam in set(cams.values())}
    plans = adapter.recompute_plans if recompute == "auto" else (recompute,)
    for plan in plans[:-1]:  # the ones a plan that recomputes more may replace
        adapter.set_recompute_plan(plan)
        try:
            _require_step(adapter, low, cams, source, shapes, batch_size, buffer_mib, dtype, others, route)
            return plan
        except BudgetError:
            continue
    adapter.set_recompute_plan(plans[-1])
    _require_step(adapter, low, cams, source, shapes, batch_size, buffer_mib, dtype, others, route)
    return plans[-1]


def _require_step(adapter, low: LowDim, cams: Mapping[str, str], source: FeatureSource,
                  shapes: Mapping[str, tuple[int, int]], batch_size: int, buffer_mib: int, dtype: torch.dtype,
                  others: Sequence[tuple[LowDim, FeatureSource, int]], route: Route) -> None:
    """BudgetError when a step of `batch_size` (per cell of the pass), measured as the adapter is set now, cannot
    fit."""
    cuda = adapter.device.type == "cuda"  # a CUDA step's whole peak; elsewhere autograd's share
    one, per_frame = frame_bytes(adapter, lambda f: _measuring_batch(low, cams, shapes, f), dtype, route)
    if not cuda:  # on CUDA the features' copy on the device is inside the measured peak
        per_frame += sum(tokens * width * 4 for tokens, width in shapes.values())  # the batch's features in fp32
    held = sum(buffer_frames(mib, src.frame_bytes(), batch_size, len(rows)) * src.frame_bytes()
               for rows, src, mib in ((low, source, buffer_mib), *others))
    frames = batch_size * (1 + len(others))
    grid = ", ".join(f"{cam} {t}x{w}" for cam, (t, w) in sorted(shapes.items()))
    what = (f"a training step of --batch-size {batch_size}{PLANS[adapter.recompute_plan].phrase} ({size(per_frame)} a "
            f"frame, measured on a 1- and a 2-frame step of features {grid})")
    hint, buffers = "lower --batch-size", "shuffle buffer"
    if others:
        what = f"{what} for each of the {1 + len(others)} cells of a backbone pass"
        hint, buffers = "lower --cells-per-pass or --batch-size", "shuffle buffers"
    if adapter.recompute_plan != adapter.recompute_plans[-1]:  # the plan that keeps least is left to try
        hint += f" or pass --recompute {adapter.recompute_plans[-1]}"
    if cuda:  # the 1-frame step's peak holds everything a step needs once; each further frame adds per_frame
        require(what, one + (frames - 1) * per_frame, *available_memory(adapter.device), hint)
        require(f"the {buffers} ({size(held)}) of --batch-size {batch_size}", held,
                *available_memory("cpu"), hint + " or --buffer-mib")
    else:
        require(f"{what} with its {buffers} ({size(held)})", held + frames * per_frame,
                *available_memory("cpu"), hint)
