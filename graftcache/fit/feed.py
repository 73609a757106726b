"""What each consumer of a split streams: which frames' features a block reads, and which frames they go with.

A control's pairing (graftcache.fit.controls) says that frame r sees the features of frame pairing[r]. Training
and scoring read features block by block and hand each frame's features to the frame that sees them
(pairing^-1), so the pairing costs nothing; `align` reads, block by block of its targets, the features those
frames see (a few runs, see graftcache.fit.controls.shuffle).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from graftcache.fit.data import LowDim
from graftcache.fit.stream import BlockMemo, BlockRead, BlockStream, FeatureSource, rows_by_block


@dataclass(frozen=True)
class SplitFeed:
    """One split (its low-dim rows, read from `source`'s cache) as the consumers stream it."""

    low: LowDim
    source: FeatureSource
    block_frames: int                    # of the source's cache
    pairing: np.ndarray | None = None    # frame r sees the features of frame pairing[r]; None: its own
    drop: bool = False                   # drop frames with NaN/inf features instead of refusing
    memo: BlockMemo | None = None        # blocks kept for the next streams, when read in this process

    def _blocks(self) -> list[np.ndarray]:
        return rows_by_block(self.low.rows, self.block_frames)

    def features(self, seed: int | None) -> BlockStream:
        """Each block's frames' features, with the frames that see them: forever in a new order each epoch
        (`seed`), or once in cache order (None)."""
        seen_by = np.argsort(self.pairing) if self.pairing is not None else None
        to_read = [BlockRead(pos if seen_by is None else seen_by[pos], (pos,)) for pos in self._blocks()]
        return BlockStream(self.low, [(self.source, self.low.rows)], to_read, seed=seed, drop=self.drop,
                           memo=self.memo)

    def with_targets(self, targets: FeatureSource, target_rows: np.ndarray) -> BlockStream:
        """Once in cache order: each block's frames' targets (`targets` at `target_rows`, one per frame) as the
        second source, the features those frames see as the first."""
        to_read = [BlockRead(pos, (pos if self.pairing is None else self.pairing[pos], pos)) for pos in self._blocks()]
        return BlockStream(self.low, [(self.source, self.low.rows), (targets, target_rows)], to_read, drop=self.drop,
                           memo=self.memo)

    @property
    def n_blocks(self) -> int:
        return len(self._blocks())
