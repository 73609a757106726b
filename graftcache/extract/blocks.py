"""Blocks: which episodes the unwritten blocks need (`episodes_for_blocks`), assembling decoded episodes into blocks of
`block_frames` frames, encoding each whole block (`fill`), and writing it on a background thread (`BlockWriter`)
while the next one is encoded. Batches are aligned to blocks, so a resumed run encodes the same batches as an
uninterrupted one and writes the same bytes."""

from __future__ import annotations

import queue
import threading
from collections.abc import Sequence
from contextlib import suppress
from typing import TYPE_CHECKING

import numpy as np
import polars as pl

from graftcache.extract.encode import encode_frames
from graftcache.extract.frames import episode_stream
from graftcache.extract.refusals import check_features
from graftcache.pooling import parse_grid
from graftcache.progress import progress
from graftcache.store import FeatureCache

if TYPE_CHECKING:
    from graftcache.extract.job import Job


def episodes_for_blocks(index: pl.DataFrame, cache: FeatureCache, todo: Sequence[int]) -> tuple[list[int], np.ndarray]:
    """Episodes that have frames in the blocks `todo`, and each cache row's block id."""
    bf = int(cache.layout["block_frames"])
    rows_block = np.arange(index.height) // bf
    needed = index.filter(pl.Series(np.isin(rows_block, list(todo))))["episode_index"].unique(maintain_order=True)
    return needed.to_list(), rows_block


def fill(cache: FeatureCache, job: Job, blocks: Sequence[int]) -> int:
    """Decode the episodes of the unfinished blocks among `blocks`, encode block by block, hand blocks to the
    writer; returns the frames encoded."""
    req, index, cameras = job.req, job.index, job.cameras
    todo = sorted(set(blocks) - cache.blocks_done())
    needed, rows_block = episodes_for_blocks(index, cache, todo)
    grids = list(map(parse_grid, req.grids))
    ep_rows = {ep: np.flatnonzero(index["episode_index"].to_numpy() == ep) for ep in needed}
    shapes = {cam: job.source.meta.image_shape[cam] for cam in cameras}
    buffers: dict[int, dict[str, np.ndarray]] = {}
    filled: dict[int, int] = {}
    todo_set = set(todo)
    writer = BlockWriter(cache)
    bar = progress(total=sum(cache.block_range(b)[1] - cache.block_range(b)[0] for b in todo), unit="frame",
                   desc=f"extract {cache.key}", enabled=req.progress)
    encoded = 0
    try:
        for ep, frames in episode_stream(job.source, needed, cameras, req.num_workers, req.frame_stride):
            rows = ep_rows[ep]  # the episode's keyframes, in order: the decoded frames after the stride
            for block in np.unique(rows_block[rows]):
                block = int(block)
                if block not in todo_set:
                    continue
                start, stop = cache.block_range(block)
                buf = buffers.setdefault(block, {c: np.empty((stop - start, *shapes[c]), np.uint8) for c in cameras})
                sel = rows[(rows >= start) & (rows < stop)]
                src = sel - rows[0]
                for cam in cameras:
                    buf[cam][sel - start] = frames[cam][src]
                filled[block] = filled.get(block, 0) + len(sel)
                if filled[block] == stop - start:
                    buf = buffers.pop(block)
                    data = {f"features/{cam}/{name}": arr
                            for cam in cameras
                            for name, arr in encode_frames(job.encoder, buf[cam], grids, batch_size=req.batch_size,
                                                           device=job.device, compute=job.compute,
                                                           dtype=req.storage_dtype).items()}
                    if not req.allow_nonfinite:
                        check_features(data, index, start, req.storage_dtype, cache.key)
                    writer.put(block, data)
                    encoded += stop - start
                    bar.update(stop - start)
        writer.close()
    finally:
        writer.close(finish=False)  # unwinding (an error, Ctrl-C, SIGTERM): no write outlives the extraction
        bar.close()
    return encoded


class BlockWriter:
    """Writes finished blocks on a background thread (Blosc and file I/O release the GIL), so
    encoding of block k+1 overlaps the compression and write of block k. At most one block waits.

    The thread never outlives the extraction: left running after an interrupt, it went on writing while the
    interpreter shut down, and zarr's event loop, stopped and closed at exit, dropped the write it had just
    submitted ("coroutine '_runner' was never awaited" after the command's last line)."""

    def __init__(self, cache: FeatureCache) -> None:
        self.cache = cache
        self.queue: queue.Queue = queue.Queue(maxsize=1)
        self.error: BaseException | None = None
        self.dropping = False  # close(finish=False): write nothing more
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        while (item := self.queue.get()) is not None:
            if self.error is None and not self.dropping:
                try:
                    self.cache.write_block(*item)
                except BaseException as e:  # surfaced in the main thread by put()/close()
                    self.error = e

    def put(self, block: int, data: dict[str, np.ndarray]) -> None:
        if self.error:
            raise self.error
        self.queue.put((block, data))

    def close(self, *, finish: bool = True) -> None:
        """Wait for the thread to end: after writing every waiting block, or (`finish` False, when unwinding) after
        the block being written, the waiting one dropped unmarked for a rerun to write. A no-op once it has ended."""
        if not self.thread.is_alive():
            return
        if not finish:
            self.dropping = True
            with suppress(queue.Empty):
                self.queue.get_nowait()
        self.queue.put(None)
        self.thread.join()
        if finish and self.error:
            raise self.error
