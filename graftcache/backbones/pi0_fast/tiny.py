"""Tiny pi0-FAST at the PaliGemma family's tiny geometry, with a FAST tokenizer of its own fitted by lerobot's FAST
processor (the FAST recipe: BPE on the quantised DCT coefficients), saved beside its weights.
"""

from __future__ import annotations

import contextlib
import math
import os
import sys
from collections.abc import Iterator

import numpy as np
import torch

from graftcache.backbones.checkpoint import quiet
from graftcache.backbones.paligemma import Pi05TinyGeometry, paligemma_tiny_tokenizer, pi05_tiny_sizes
from graftcache.backbones.pi0_fast.fast import FAST_DIR, MODELING, fast_processors, policy_tokenizers
from graftcache.backbones.tiny import TinyBuild, action_features, require_stats, visual_features
from graftcache.backbones.tiny_assets import PALIGEMMA_DIR

#: Tiny FAST tokenizer: FAST's default quantisation scale, lowered where the alphabet of quantised coefficients
#: would not fit, and a vocabulary inside the tiny PaliGemma tokenizer's merge range (ids 261..770: action tokens
#: map to ids 770 - t with fast_skip_tokens 0, above every byte token, so "|" and "Action: " stay recognisable).
FAST_SCALE = 10.0
TINY_FAST_ALPHABET = 301
TINY_FAST_VOCAB = 480
TINY_FAST_CORPUS = 2000



def fit_tiny_fast(stats: dict, tiny: TinyBuild):
    """A FAST tokenizer for a tiny policy, fitted with lerobot's FAST processor on seeded smooth chunks spanning
    the dataset's normalised action range (MEAN_STD, the tiny config's). Two constant chunks at +-M (M the
    largest normalised |action|) pin the alphabet to the bound sqrt(chunk) * M * scale that every in-range
    chunk's DCT coefficients obey (|c_k| <= ||x||_2), so no in-range chunk loses a coefficient."""
    from lerobot.policies.molmoact2.molmoact2_hf_model.action_tokenizer import UniversalActionProcessor

    act = stats["action"]
    std = act["std"].double().clamp(min=1e-6)
    lo, hi = ((act["min"].double() - act["mean"]) / std).numpy(), ((act["max"].double() - act["mean"]) / std).numpy()
    bound = float(max(np.abs(lo).max(), np.abs(hi).max(), 1e-3))
    scale = min(FAST_SCALE, (TINY_FAST_ALPHABET - 1) / 2 / (math.sqrt(tiny.chunk_size) * bound))
    rng = np.random.default_rng(tiny.seed)
    shape = (TINY_FAST_CORPUS, tiny.chunk_size, tiny.action_dim)
    walk = rng.uniform(lo, hi, (shape[0], 1, shape[2])) + np.cumsum(rng.normal(0, 0.05, shape) * (hi - lo), axis=1)
    chunks = [*np.clip(walk, lo, hi), np.full(shape[1:], bound), np.full(shape[1:], -bound)]
    with quiet(), _stdout_fd_silenced():
        return UniversalActionProcessor.fit(chunks, scale=scale, vocab_size=TINY_FAST_VOCAB,
                                            time_horizon=tiny.chunk_size, action_dim=tiny.action_dim)

@contextlib.contextmanager
def _stdout_fd_silenced() -> Iterator[None]:
    """The BPE trainer's progress bar (on in lerobot's `fit`) writes blank lines to file descriptor 1 itself,
    past Python's sys.stdout, into the stdout that commands keep for their results."""
    sys.stdout.flush()
    saved, devnull = os.dup(1), os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, 1)
    try:
        yield
    finally:
        os.dup2(saved, 1)
        os.close(saved)
        os.close(devnull)


def build_tiny(tiny: TinyBuild, stats: dict | None, device: str):
    """Random-init tiny pi0-FAST with its fitted FAST tokenizer, its lerobot pre/post processors (deterministic for
    `tiny.seed`) and its geometry (the vocabulary is the tiny tokenizer's, so every id the LM emits decodes)."""
    from lerobot.policies.pi0_fast.configuration_pi0_fast import PI0FastConfig
    from lerobot.policies.pi0_fast.modeling_pi0_fast import PI0FastPolicy

    stats = require_stats(stats)
    geometry = Pi05TinyGeometry(vocab_size=len(paligemma_tiny_tokenizer()))
    tokens = tiny.chunk_size * tiny.action_dim + 6  # <bos> "Action: " (3) ... "|" <eos>: never truncated
    config = PI0FastConfig(
        chunk_size=tiny.chunk_size, n_action_steps=tiny.chunk_size,
        image_resolution=(geometry.image_size, geometry.image_size),
        max_state_dim=max(tiny.state_dim, 8), max_action_dim=max(tiny.action_dim, 8),
        tokenizer_max_length=geometry.tokenizer_max_length, device=device, dtype="float32",
        text_tokenizer_name=str(PALIGEMMA_DIR), action_tokenizer_name=FAST_DIR, fast_skip_tokens=0,
        max_action_tokens=tokens, max_decoding_steps=tokens,
        input_features=visual_features(tiny, geometry.image_size), output_features=action_features(tiny),
    )
    fast = fit_tiny_fast(stats, tiny)
    with torch.random.fork_rng(devices=[]), pi05_tiny_sizes(geometry, MODELING), \
            policy_tokenizers(fast, PALIGEMMA_DIR):
        torch.manual_seed(tiny.seed)
        policy = PI0FastPolicy(config)
    pre, post = fast_processors(config, stats, fast)
    return policy.to(device), pre, post, geometry
