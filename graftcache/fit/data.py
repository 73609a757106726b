"""Stage 2 data path: everything a fit needs comes from the feature cache, never from videos.

A `FrameTable` holds, for the frames of one suite, the pooled features per camera (kept in the
stored precision to halve memory), the state, the action chunk starting at each frame with its
padding mask, and the task index. The held-out split is by episode within each task, with a fixed
split seed that is recorded in every results row.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import polars as pl
import torch

from graftcache.errors import FitError
from graftcache.nonfinite import DROP_FLAG, nonfinite_rows
from graftcache.pooling import format_grid, parse_grid, pool_grid
from graftcache.runtime import resolve_dtype
from graftcache.store import FeatureCache

#: How much of a stored grid (as fp32) `read_grid` holds at a time while it pools to a coarser one.
POOL_CHUNK_BYTES = 2**28


@dataclass(frozen=True)
class Split:
    """Episode split, per task: `eval_fraction` of each task's episodes (at least one when a task
    has two or more) are held out, chosen by a generator seeded with `seed`."""

    train_episodes: tuple[int, ...]
    eval_episodes: tuple[int, ...]
    seed: int
    eval_fraction: float


def split_episodes(index: pl.DataFrame, *, eval_fraction: float, seed: int) -> Split:
    """Split the episodes of `index` (columns episode_index, task_index) by task."""
    if not 0.0 < eval_fraction < 1.0:
        raise FitError(f"--eval-fraction must be in (0, 1), got {eval_fraction}")
    rng = np.random.default_rng(seed)
    per_task = (index.group_by("task_index").agg(pl.col("episode_index").unique().sort()).sort("task_index"))
    train, held = [], []
    for episodes in per_task["episode_index"].to_list():
        order = rng.permutation(len(episodes))
        n_eval = max(1, round(eval_fraction * len(episodes))) if len(episodes) >= 2 else 0
        held += [episodes[i] for i in order[:n_eval]]
        train += [episodes[i] for i in order[n_eval:]]
    if not held:
        raise FitError("no episode can be held out: every task has a single episode")
    return Split(tuple(sorted(train)), tuple(sorted(held)), seed, eval_fraction)


@dataclass
class FrameTable:
    """In-memory training/eval material for one suite, from the cache only."""

    rows: np.ndarray                    # cache row ids, [N]
    episode_index: np.ndarray           # [N]
    features: dict[str, torch.Tensor]   # camera -> [N, T, C] stored precision
    state: torch.Tensor                 # [N, S] float32 (raw units)
    actions: torch.Tensor               # [N, chunk, A] float32 (raw units)
    action_pad: torch.Tensor            # [N, chunk] bool, True past the episode end
    task_index: torch.Tensor            # [N] int64
    tasks: tuple[str, ...]

    def __len__(self) -> int:
        return len(self.rows)

    def take(self, positions: np.ndarray) -> FrameTable:
        """The frames at `positions` (the one way a table is narrowed: episode split, eval cap)."""
        t = torch.from_numpy(positions)
        return FrameTable(self.rows[positions], self.episode_index[positions],
                          {c: f[t] for c, f in self.features.items()}, self.state[t], self.actions[t],
                          self.action_pad[t], self.task_index[t], self.tasks)

    def subset(self, episodes: Sequence[int]) -> FrameTable:
        return self.take(np.flatnonzero(np.isin(self.episode_index, np.asarray(episodes))))

    def evenly(self, max_frames: int | None) -> FrameTable:
        """At most `max_frames` evenly spaced frames (deterministic), the whole table otherwise."""
        if max_frames is None or len(self) <= max_frames:
            return self
        return self.take(np.linspace(0, len(self) - 1, max_frames).round().astype(int))


def suite_index_table(cache: FeatureCache, suite: str) -> pl.DataFrame:
    """The cache index restricted to one LIBERO suite; a suite with no episodes is an error."""
    suites = cache.manifest["suites"]
    if suite not in suites:
        raise FitError(f"unknown suite {suite!r}; known: {', '.join(suites)}")
    idx = cache.index().with_row_index("row")
    sub = idx.filter(pl.col("suite_index") == suites.index(suite))
    if sub.height == 0:
        present = sorted({suites[i] for i in idx["suite_index"].unique().to_list()})
        raise FitError(f"cache {cache.key}: suite {suite!r} has no episodes (present: {', '.join(present)})")
    return sub


def read_grid(cache: FeatureCache, camera: str, grid: tuple[int, int], rows: np.ndarray) -> torch.Tensor:
    """Features of `camera` at `grid` for cache rows `rows`, [len(rows), H*W, C] in stored precision: the grid
    itself when the cache stores it, else adaptive-average-pooled at read time from the encoder's own grid as
    the manifest names it (`native_grid`; caches from before it record none: the finest stored grid).

    What pooling here costs in precision: extraction pools the fp32 activations and rounds the mean once to
    the stored dtype; here the stored, already rounded values are averaged in fp32 and the mean rounded
    again. Each input is off by at most half a unit in the last place (fp16: 2^-11 relative, bf16: 2^-8),
    and so is each rounded mean, so a value differs from the extract-time pooled one by at most 3 x 2^-11
    (fp16; bf16: 3 x 2^-8) of the largest magnitude in its pooling window: about one fp16 step. fp32
    caches pool exactly what extraction would have. Exact-multiple grids (16x16 -> 8x8) average whole
    blocks of cells; others average overlapping windows.

    The stored grid is read and pooled `POOL_CHUNK_BYTES` of fp32 at a time (whole cache blocks), so a
    suite of 16x16x768 frames never sits in memory unpooled.
    """
    name = format_grid(grid)
    stored = cache.manifest["grids"]
    if name in stored:
        return cache.read_features(camera, name, rows)
    source = cache.manifest.get("native_grid") or max(stored, key=lambda g: math.prod(parse_grid(g)))
    (h, w), width = parse_grid(source), cache.layout["arrays"][cache.feature_path(camera, source)][-1]
    block = int(cache.layout["block_frames"])
    per_chunk = block * max(1, POOL_CHUNK_BYTES // (block * h * w * width * 4))
    rows = np.asarray(rows)
    out = torch.empty((len(rows), grid[0] * grid[1], width), dtype=resolve_dtype(cache.manifest["dtype"]))
    for chunk in np.unique(rows // per_chunk):
        at = np.flatnonzero(rows // per_chunk == chunk)
        src = cache.read_features(camera, source, rows[at])
        out[torch.from_numpy(at)] = pool_grid(src.float().reshape(len(at), h, w, width), grid).to(out.dtype)
    return out


def action_chunks(actions: np.ndarray, episode: np.ndarray, chunk: int) -> tuple[np.ndarray, np.ndarray]:
    """For each frame, the next `chunk` actions of the same episode, padded with the last action.

    Frames must be in episode order, consecutive within an episode. Returns (chunks [N, chunk, A],
    pad [N, chunk] True where the step lies past the episode end).
    """
    n = len(actions)
    starts = np.r_[0, np.flatnonzero(np.diff(episode)) + 1]
    ends = np.r_[starts[1:], n]
    ep_end = np.repeat(ends, ends - starts)  # exclusive end of each frame's episode
    steps = np.arange(n)[:, None] + np.arange(chunk)[None, :]
    pad = steps >= ep_end[:, None]
    steps = np.minimum(steps, ep_end[:, None] - 1)
    return actions[steps], pad


def frame_chunks(cache: FeatureCache, frames: pl.DataFrame, chunk: int) -> tuple[np.ndarray, np.ndarray]:
    """Action chunks [N, chunk, A] and pad masks [N, chunk] of `frames` (rows of the cache index), taken
    from the cache's full-rate action stream, so a frame stride thins the observations, not the actions."""
    episodes = frames["episode_index"].unique().implode()
    stream = cache.action_stream().filter(pl.col("episode_index").is_in(episodes)).sort("episode_index", "frame_index")
    all_chunks, all_pad = action_chunks(np.stack(stream["action"].to_numpy()).astype(np.float32),
                                        stream["episode_index"].to_numpy(), chunk)
    key = stream.select("episode_index", "frame_index").with_row_index("pos")
    pos = frames.select("episode_index", "frame_index").join(key, on=["episode_index", "frame_index"], how="left",
                                                            maintain_order="left")["pos"]
    if pos.null_count():
        raise FitError(f"cache {cache.key}: {pos.null_count()} frame(s) have no entry in the action stream")
    pos = pos.to_numpy()
    return all_chunks[pos], all_pad[pos]


def load_frames(cache: FeatureCache, suite: str, *, cameras: Sequence[str], grid: tuple[int, int] | None,
                chunk: int, extra: str | None = None) -> FrameTable:
    """All frames of `suite` with features at `grid` (or the stored extra array `extra`, e.g. the
    native tower's post-connector tokens)."""
    sub = suite_index_table(cache, suite)
    rows = sub["row"].to_numpy()
    episode = sub["episode_index"].to_numpy()
    missing = [c for c in cameras if c not in cache.manifest["cameras"]]
    if missing:
        raise FitError(f"cache {cache.key} has no camera {missing}; it has {cache.manifest['cameras']}")
    if extra is not None:
        feats = {c: cache.read_features(c, extra, rows) for c in cameras}
    else:
        assert grid is not None
        feats = {c: read_grid(cache, c, grid, rows) for c in cameras}
    chunks, pad = frame_chunks(cache, sub, chunk)
    return FrameTable(
        rows=rows,
        episode_index=episode,
        features=feats,
        state=torch.from_numpy(np.stack(sub["state"].to_numpy()).astype(np.float32)),
        actions=torch.from_numpy(chunks),
        action_pad=torch.from_numpy(pad),
        task_index=torch.from_numpy(sub["task_index"].to_numpy().astype(np.int64)),
        tasks=tuple(cache.manifest["tasks"]),
    )


def drop_nonfinite(table: FrameTable, cache: FeatureCache, *, drop: bool) -> tuple[FrameTable, int]:
    """`table` without the frames whose features, state or action chunk hold a NaN/inf, and how many those
    were. Without `drop` any such frame is a FitError naming the cache, episode and frame: a NaN would flow
    into the normalisation, the loss and the MSE. (Caches extracted before stage 1 refused them, or with
    `extract --allow-nonfinite`, can hold them.)"""
    parts = {"state": table.state, "action chunk": table.actions,
             **{f"features/{c}": f for c, f in table.features.items()}}
    bad = {name: nonfinite_rows(values) for name, values in parts.items()}
    any_bad = np.logical_or.reduce(list(bad.values()))
    if not any_bad.any():
        return table, 0
    if not drop:
        name = next(n for n, b in bad.items() if b.any())
        at = int(np.flatnonzero(bad[name])[0])
        frame = int(cache.index()["frame_index"][int(table.rows[at])])
        raise FitError(f"cache {cache.key}: {name} is NaN/inf at episode {int(table.episode_index[at])} frame {frame} "
                       f"({int(any_bad.sum())} of {len(table)} frame(s) non-finite); pass {DROP_FLAG} to drop them "
                       f"(the results row records how many)")
    return table.take(np.flatnonzero(~any_bad)), int(any_bad.sum())
