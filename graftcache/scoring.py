"""Offline action MSE on held-out frames: deterministic, from the denoised chunk.

We score the *denoised* action chunk, not the stochastic flow loss: the flow loss depends on the
sampled noise level, while the chunk is what the policy would execute. Each frame gets its own
fixed start noise from a generator seeded with (noise_seed, cache row), so every encoder, control
and rerun is scored on exactly the same noise, and CPU reruns are bit-identical.
Offline action MSE is a proxy: it is known to predict closed-loop success only weakly.

CI-MSE (critical-interval MSE) is the same squared error restricted to the chunk steps that fall in a
critical interval of their episode (graftcache/critical.py states the rule): the mean over every critical
(frame, chunk step) pair and action dimension, in normalised units, padded steps never included. It is null
for a split (or an episode) whose scored chunks reach no critical step.

The full-chunk error is also split by action dimension, from the same per-frame squared errors: the arm (the
end-effector dimensions, the first action_dim - 1: LIBERO's 6-d delta pose) and the gripper (the last
dimension). Per frame the full-chunk error is their mix weighted by dimensions, ((A-1) * arm + gripper) / A, so a
score that ranks encoders by the arm alone shows whether the gripper's one dimension drives eval_mse.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

NOISE_SEED = 1_000_003


@dataclass(frozen=True)
class Score:
    mse: float            # full chunk, normalised units, padded steps excluded
    mse_first: float      # first action of the chunk, normalised units
    mse_raw: float        # full chunk, raw action units
    mse_arm: float | None  # full chunk, normalised units, the first action_dim - 1 dims (None: 1-d actions)
    mse_gripper: float    # full chunk, normalised units, the last action dim
    n_frames: int
    per_episode: dict[int, float]  # normalised full-chunk MSE per held-out episode (for bootstraps)
    ci_mse: float | None  # normalised MSE over the critical chunk steps (None: no critical step was scored)
    ci_per_episode: dict[int, float | None]  # the same per held-out episode (same keys as per_episode)


def frame_noise(rows: np.ndarray, chunk: int, width: int, seed: int = NOISE_SEED) -> torch.Tensor:
    """Start noise [N, chunk, width], one fixed draw per cache row."""
    out = torch.empty(len(rows), chunk, width)
    for i, row in enumerate(rows):
        out[i] = torch.randn(chunk, width, generator=torch.Generator().manual_seed(seed + int(row)))
    return out


def masked_mse(pred: torch.Tensor, target: torch.Tensor, pad: torch.Tensor) -> torch.Tensor:
    """Per-frame MSE over real (non-padded) chunk steps and action dims: [N]."""
    valid = (~pad).float()
    per_step = ((pred - target) ** 2).mean(dim=-1)
    return (per_step * valid).sum(-1) / valid.sum(-1).clamp(min=1.0)


def deterministic_mean(values: torch.Tensor) -> float:
    """The mean of every element, summed in float64 by numpy in one thread: torch's float32 sum of a tensor past
    its parallel grain adds one partial sum per intra-op thread, so a score would depend on the thread count."""
    return float(np.mean(values.detach().cpu().numpy(), dtype=np.float64))


def critical_mse(pred: torch.Tensor, target: torch.Tensor, critical: torch.Tensor) -> float | None:
    """Mean squared error over the (frame, step) pairs `critical` [N, chunk] marks, all action dims; None
    when it marks none."""
    if not bool(critical.any()):
        return None
    per_step = ((pred - target) ** 2).mean(dim=-1)
    return deterministic_mean(per_step[critical])


def score_chunks(pred_norm: torch.Tensor, target_norm: torch.Tensor, pred_raw: torch.Tensor,
                 target_raw: torch.Tensor, pad: torch.Tensor, episodes: np.ndarray, *,
                 critical: torch.Tensor) -> Score:
    """Aggregate predictions [N, chunk, A] against targets into a Score; `critical` [N, chunk] marks the chunk
    steps inside a critical interval (graftcache.fit.data.LowDim.critical_chunks), for CI-MSE."""
    per_frame = masked_mse(pred_norm, target_norm, pad)
    first = ((pred_norm[:, 0] - target_norm[:, 0]) ** 2).mean(-1)
    raw = masked_mse(pred_raw, target_raw, pad)
    arm = masked_mse(pred_norm[..., :-1], target_norm[..., :-1], pad) if pred_norm.shape[-1] > 1 else None
    gripper = masked_mse(pred_norm[..., -1:], target_norm[..., -1:], pad)
    critical = critical & ~pad
    per_ep, ci_per_ep = {}, {}
    for e in np.unique(episodes):
        at = torch.from_numpy(episodes == e)
        per_ep[int(e)] = deterministic_mean(per_frame[at])
        ci_per_ep[int(e)] = critical_mse(pred_norm[at], target_norm[at], critical[at])
    ci = critical_mse(pred_norm, target_norm, critical)
    return Score(deterministic_mean(per_frame), deterministic_mean(first), deterministic_mean(raw),
                 None if arm is None else deterministic_mean(arm), deterministic_mean(gripper), len(per_frame), per_ep,
                 ci, ci_per_ep)
