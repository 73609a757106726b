"""The bounded shuffle buffer between the block stream and the training batches.

Blocks arrive in a seeded block order (graftcache.fit.stream); the buffer holds `capacity` frames, and each
batch takes `k` distinct slots drawn by the cell's generator and refills them with the stream's next frames.
Every frame that enters is drawn exactly once, and at most `capacity` + what the stream prefetches is ever in
memory, whatever the size of the split. Frames drawn together come from up to capacity / block_frames blocks,
so the buffer is the knob between memory and how well batches mix episodes.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import torch

from graftcache.errors import FitError
from graftcache.fit.stream import Block, Features, FrameQueue

MIB = 1 << 20


def buffer_frames(mib: int, frame_bytes: int, batch_size: int, n_frames: int) -> int:
    """Frames a buffer of `mib` MiB holds (frames of `frame_bytes`): at least one batch, at most the split."""
    return max(batch_size, min(n_frames, mib * MIB // max(frame_bytes, 1)))


class ShuffleBuffer:
    """Batches drawn from a bounded buffer over an endless block stream (one source's features)."""

    def __init__(self, blocks: Iterator[Block], capacity: int, *, empty_limit: int | None = None) -> None:
        self.capacity = capacity
        self._queue = FrameQueue(blocks, empty_limit=empty_limit)
        self._owners = np.empty(capacity, dtype=np.int64)
        self._features: Features | None = None

    def _next(self, k: int) -> tuple[np.ndarray, Features]:
        taken = self._queue.take(k)
        if taken is None or len(taken[0]) < k:
            raise FitError("the training stream ended: it must repeat its blocks forever")
        return taken[0], taken[1][0]

    def draw(self, k: int, generator: torch.Generator) -> tuple[np.ndarray, Features]:
        """(owners [k], features [k, ...]) of `k` distinct buffered frames chosen by `generator`, which the
        stream's next frames replace. The first draw fills the buffer."""
        if k > self.capacity:
            raise FitError(f"a batch of {k} cannot be drawn from a buffer of {self.capacity} frames")
        if self._features is None:
            self._owners[:], self._features = self._next(self.capacity)
        slots = torch.randperm(self.capacity, generator=generator)[:k]
        at = slots.numpy()
        owners = self._owners[at].copy()
        batch = {c: v[slots] for c, v in self._features.items()}
        self._owners[at], fresh = self._next(k)
        for c, v in self._features.items():
            v[slots] = fresh[c]
        return owners, batch
