"""Decoding: worker processes decode whole episodes (PyAV / PNG, one thread each) and hand over the keyframes
(frame_index % stride == 0); a decode error travels back as one line."""

from __future__ import annotations

import sys
from collections.abc import Iterator, Sequence

import numpy as np
from torch.utils.data import DataLoader, Dataset

from graftcache.datasets import LeRobotSource
from graftcache.errors import DatasetError
from graftcache.runtime import single_thread_worker


class _EpisodeFrames(Dataset):
    """Decodes one whole episode per item (all requested cameras) inside a worker process."""

    def __init__(self, source: LeRobotSource, episodes: Sequence[int], cameras: Sequence[str], stride: int) -> None:
        self.source, self.episodes, self.cameras, self.stride = source, list(episodes), list(cameras), stride
        self.lengths = {e.index: e.length for e in source.meta.episodes}

    def __len__(self) -> int:
        return len(self.episodes)

    def __getitem__(self, i: int) -> tuple[int, dict[str, np.ndarray] | str]:
        """(episode, frames), or (episode, one-line error text): an exception raised in a worker process
        would reach the main process wrapped in torch's multi-line "Caught ... in DataLoader worker"
        report, so decode errors travel back as values and are raised there as DatasetError."""
        ep = self.episodes[i]
        try:
            frames = self.source.decode_episode(ep, self.cameras)
            for cam, video in frames.items():
                if video.shape[0] != self.lengths[ep]:
                    raise DatasetError(f"{self.source.meta.root}: episode {ep} camera {cam} decoded "
                                       f"{video.shape[0]} frames, metadata says {self.lengths[ep]}")
            # keyframes only (frame_index % stride == 0), so only they cross the process boundary
            return ep, {cam: video[:: self.stride] for cam, video in frames.items()}
        except DatasetError as e:
            return ep, str(e)
        except Exception as e:  # a decoder library's own error on a damaged file
            return ep, f"{self.source.meta.root}: episode {ep}: cannot decode ({type(e).__name__}: {e})"


def episode_stream(source: LeRobotSource, episodes: Sequence[int], cameras: Sequence[str], num_workers: int,
                    stride: int) -> Iterator[tuple[int, dict[str, np.ndarray]]]:
    ds = _EpisodeFrames(source, episodes, cameras, stride)
    items: Iterator[tuple[int, dict[str, np.ndarray] | str]] = (ds[i] for i in range(len(ds)))
    if num_workers:
        items = iter(DataLoader(ds, batch_size=None, shuffle=False, num_workers=num_workers,
                                worker_init_fn=single_thread_worker, prefetch_factor=2, persistent_workers=False,
                                multiprocessing_context="spawn" if sys.platform == "darwin" else None))
    for ep, frames in items:
        if isinstance(frames, str):
            raise DatasetError(" ".join(frames.split()))
        yield ep, frames
