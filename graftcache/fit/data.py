"""Stage 2 data path: everything a fit needs comes from the feature cache, never from videos.

Only the low-dim part of a suite is held in memory (`LowDim`: state, task, where each frame's action chunk
lies in the action stream); features are read block by block where they are used (graftcache.fit.stream,
through `read_grid`). The held-out split is by episode within each task, by one of two rules (SPLITS) recorded
in every results row with the split seed.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import polars as pl
import torch

from graftcache.critical import critical_steps
from graftcache.errors import FitError
from graftcache.nonfinite import DROP_FLAG, nonfinite_rows
from graftcache.pooling import format_grid, parse_grid, pool_grid
from graftcache.runtime import resolve_dtype
from graftcache.store import FeatureCache

#: How much of a stored grid (as fp32) `read_grid` holds at a time while it pools to a coarser one.
POOL_READ_BYTES = 2**28


@dataclass(frozen=True)
class Split:
    """Episode split, per task, by the rule `rule` names (SPLITS): `eval_fraction` of each task's episodes held
    out (`seed` seeds the graftcache rule's draw; the lerobot rule draws nothing)."""

    train_episodes: tuple[int, ...]
    eval_episodes: tuple[int, ...]
    seed: int
    eval_fraction: float
    rule: str = "graftcache"


def _drawn(episodes: list[int], fraction: float, rng: np.random.Generator) -> list[int]:
    """graftcache's rule: round(n * fraction) of a task's n episodes (at least one when it has two or more),
    drawn by the split seed's generator, so no part of a recording session is favoured."""
    n_eval = max(1, round(fraction * len(episodes))) if len(episodes) >= 2 else 0
    return [episodes[i] for i in rng.permutation(len(episodes))[:n_eval]]


def _last(episodes: list[int], fraction: float, _: np.random.Generator) -> list[int]:
    """lerobot's rule (`lerobot-train --dataset.eval_split`, lerobot.datasets.factory.make_train_eval_datasets):
    the last ceil(n * fraction) of a task's n episodes in episode order, computed as lerobot computes it (the same
    float product, so the same episodes), so graftcache's scores and lerobot's validation loss see one split."""
    return episodes[len(episodes) - math.ceil(len(episodes) * fraction):]


#: How each split rule picks a task's held-out episodes from its sorted episodes (graftcache.requests.EVAL_SPLITS
#: names them for the CLI; tests/test_settings.py keeps the two equal). "graftcache" is the default, and cells split
#: by it keep the run_ids they had before the rule was a setting (graftcache.fit.plan.Cell.run_id).
SPLITS: dict[str, Callable[[list[int], float, np.random.Generator], list[int]]] = {
    "graftcache": _drawn,
    "lerobot": _last,
}


def split_episodes(index: pl.DataFrame, *, eval_fraction: float, seed: int, rule: str = "graftcache") -> Split:
    """Split the episodes of `index` (columns episode_index, task_index) by task, by `rule` (a SPLITS name)."""
    if not 0.0 < eval_fraction < 1.0:
        raise FitError(f"--eval-fraction must be in (0, 1), got {eval_fraction}")
    if rule not in SPLITS:
        raise FitError(f"--split {rule!r}: choose one of {', '.join(SPLITS)}")
    rng = np.random.default_rng(seed)
    per_task = (index.group_by("task_index").agg(pl.col("episode_index").unique().sort()).sort("task_index"))
    train, held = [], []
    for episodes in per_task["episode_index"].to_list():
        out = set(SPLITS[rule](episodes, eval_fraction, rng))
        held += [e for e in episodes if e in out]
        train += [e for e in episodes if e not in out]
    if not held:
        raise FitError("no episode can be held out: every task has a single episode")
    if not train:
        raise FitError(f"--split {rule} with --eval-fraction {eval_fraction} holds out every episode: nothing to "
                       "train on")
    return Split(tuple(sorted(train)), tuple(sorted(held)), seed, eval_fraction, rule)


@dataclass
class LowDim:
    """The in-memory part of a suite's frames: ~120 bytes a frame (16 MB for every LIBERO frame), never features.

    Action chunks are not stored per frame ([chunk, A] floats would be 1.4 KB a frame at lerobot's chunk of 50):
    each frame keeps where it starts in the suite's full-rate action stream and where its episode ends there,
    and `action_chunks` builds the chunks of a batch when the batch is drawn.
    """

    rows: np.ndarray            # cache row ids [N]
    index: np.ndarray           # dataset frame index [N]: the same frame in every cache of one dataset
    episode_index: np.ndarray   # [N]
    frame_index: np.ndarray     # [N]
    state: torch.Tensor         # [N, S] float32 (raw units)
    task_index: torch.Tensor    # [N] int64
    stream_start: np.ndarray    # [N] the frame's position in `actions`
    stream_end: np.ndarray      # [N] exclusive end of the frame's episode in `actions`
    actions: torch.Tensor       # [M, A] float32: the full-rate action stream of the suite's episodes (shared)
    chunk: int                  # steps of an action chunk
    tasks: tuple[str, ...]
    critical: np.ndarray        # [M] bool: stream steps inside a critical interval (graftcache/critical.py)

    def __len__(self) -> int:
        return len(self.rows)

    def take(self, positions: np.ndarray) -> LowDim:
        """The frames at `positions` (the one way a table is narrowed: episode split, eval cap, non-finite drops)."""
        t = torch.from_numpy(positions)
        return LowDim(self.rows[positions], self.index[positions], self.episode_index[positions],
                      self.frame_index[positions], self.state[t], self.task_index[t], self.stream_start[positions],
                      self.stream_end[positions], self.actions, self.chunk, self.tasks, self.critical)

    def subset(self, episodes: Sequence[int]) -> LowDim:
        return self.take(np.flatnonzero(np.isin(self.episode_index, np.asarray(episodes))))

    def evenly(self, max_frames: int | None) -> LowDim:
        """At most `max_frames` evenly spaced frames (deterministic), the whole table otherwise."""
        if max_frames is None or len(self) <= max_frames:
            return self
        return self.take(np.linspace(0, len(self) - 1, max_frames).round().astype(int))

    def action_chunks(self, positions: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
        """(chunks [k, chunk, A], pad [k, chunk]) of the frames at `positions`: the next `chunk` actions of the
        frame's episode at full rate, padded with the episode's last action (pad True past the episode end)."""
        steps, pad = chunk_steps(self.stream_start[positions], self.stream_end[positions], self.chunk)
        return self.actions[torch.from_numpy(steps)], torch.from_numpy(pad)

    def critical_chunks(self, positions: np.ndarray) -> torch.Tensor:
        """Bool [k, chunk]: which steps of the frames' action chunks lie in a critical interval (never a padded
        step), the steps CI-MSE scores."""
        steps, pad = chunk_steps(self.stream_start[positions], self.stream_end[positions], self.chunk)
        return torch.from_numpy(self.critical[steps] & ~pad)

    def nonfinite(self) -> dict[str, np.ndarray]:
        """Bool [N] per low-dim part ("state", "action chunk"): frames holding a NaN/inf there."""
        bad_action = np.r_[0, np.cumsum(nonfinite_rows(self.actions))]
        last = np.minimum(self.stream_start + self.chunk, self.stream_end)  # a chunk's padding repeats last-1
        return {"state": nonfinite_rows(self.state), "action chunk": bad_action[last] > bad_action[self.stream_start]}


def suite_index_table(cache: FeatureCache, suite: str) -> pl.DataFrame:
    """The cache index restricted to one LIBERO suite; a suite with no episodes is an error."""
    suites = cache.manifest.suites
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
    the manifest names it (`unpooled_grid`; a cache of pooled grids only: the finest stored grid).

    What pooling here costs in precision: extraction pools the fp32 activations and rounds the mean once to
    the stored dtype; here the stored, already rounded values are averaged in fp32 and the mean rounded
    again. Each input is off by at most half a unit in the last place (fp16: 2^-11 relative, bf16: 2^-8),
    and so is each rounded mean, so a value differs from the extract-time pooled one by at most 3 x 2^-11
    (fp16; bf16: 3 x 2^-8) of the largest magnitude in its pooling window: about one fp16 step. fp32
    caches pool exactly what extraction would have. Exact-multiple grids (16x16 -> 8x8) average whole
    blocks of cells; others average overlapping windows.

    The stored grid is read and pooled `POOL_READ_BYTES` of fp32 at a time (whole cache blocks), so a
    suite of 16x16x768 frames never sits in memory unpooled.
    """
    name = format_grid(grid)
    stored = cache.manifest.grids
    if name in stored:
        return cache.read_features(camera, name, rows)
    source = cache.manifest.unpooled_grid or max(stored, key=lambda g: math.prod(parse_grid(g)))
    (h, w), width = parse_grid(source), cache.layout["arrays"][cache.feature_path(camera, source)][-1]
    block = int(cache.layout["block_frames"])
    per_read = block * max(1, POOL_READ_BYTES // (block * h * w * width * 4))
    rows = np.asarray(rows)
    out = torch.empty((len(rows), grid[0] * grid[1], width), dtype=resolve_dtype(cache.manifest.storage_dtype))
    for part in np.unique(rows // per_read):
        at = np.flatnonzero(rows // per_read == part)
        src = cache.read_features(camera, source, rows[at])
        out[torch.from_numpy(at)] = pool_grid(src.float().reshape(len(at), h, w, width), grid).to(out.dtype)
    return out


def chunk_steps(start: np.ndarray, end: np.ndarray, chunk: int) -> tuple[np.ndarray, np.ndarray]:
    """The action chunk rule, written once: for frames starting at `start` in an action sequence whose episode
    ends (exclusive) at `end`, the positions of the next `chunk` actions, past the end repeating the episode's
    last action, and pad [k, chunk] True for those steps."""
    steps = start[:, None] + np.arange(chunk)[None, :]
    return np.minimum(steps, end[:, None] - 1), steps >= end[:, None]


def action_chunks(actions: np.ndarray, episode: np.ndarray, chunk: int) -> tuple[np.ndarray, np.ndarray]:
    """For each frame, the next `chunk` actions of the same episode, padded with the last action.

    Frames must be in episode order, consecutive within an episode. Returns (chunks [N, chunk, A],
    pad [N, chunk] True where the step lies past the episode end).
    """
    n = len(actions)
    starts = np.r_[0, np.flatnonzero(np.diff(episode)) + 1]
    ends = np.r_[starts[1:], n]
    steps, pad = chunk_steps(np.arange(n), np.repeat(ends, ends - starts), chunk)
    return actions[steps], pad


def load_lowdim(cache: FeatureCache, suite: str, *, chunk: int) -> LowDim:
    """Every frame of `suite` (index, state, task, where its action chunk lies in the full-rate action stream):
    a frame stride thins the observations, not the actions."""
    sub = suite_index_table(cache, suite)
    episodes = sub["episode_index"].unique().implode()
    stream = (cache.action_stream().filter(pl.col("episode_index").is_in(episodes))
              .sort("episode_index", "frame_index").with_row_index("pos"))
    ends = stream.group_by("episode_index").agg(pl.len().alias("n"), pl.col("pos").min().alias("first"))
    key = stream.select("episode_index", "frame_index", "pos").join(ends, on="episode_index")
    at = sub.select("episode_index", "frame_index").join(key, on=["episode_index", "frame_index"], how="left",
                                                        maintain_order="left")
    if at["pos"].null_count():
        raise FitError(f"cache {cache.key}: {at['pos'].null_count()} frame(s) have no entry in the action stream")
    actions = np.stack(stream["action"].to_numpy()).astype(np.float32)
    return LowDim(
        rows=sub["row"].to_numpy().astype(np.int64),
        index=sub["index"].to_numpy().astype(np.int64),
        episode_index=sub["episode_index"].to_numpy().astype(np.int64),
        frame_index=sub["frame_index"].to_numpy().astype(np.int64),
        state=torch.from_numpy(np.stack(sub["state"].to_numpy()).astype(np.float32)),
        task_index=torch.from_numpy(sub["task_index"].to_numpy().astype(np.int64)),
        stream_start=at["pos"].to_numpy().astype(np.int64),
        stream_end=(at["first"] + at["n"]).to_numpy().astype(np.int64),
        actions=torch.from_numpy(actions),
        chunk=chunk,
        tasks=tuple(cache.manifest.tasks),
        critical=critical_steps(actions, stream["episode_index"].to_numpy()),
    )


def nonfinite_message(cache: FeatureCache | str, what: str, episode: int, frame: int, count: str) -> str:
    """The one-line refusal of a non-finite frame, naming cache, part, episode and frame."""
    key = cache if isinstance(cache, str) else cache.key
    return (f"cache {key}: {what} is NaN/inf at episode {episode} frame {frame} ({count}); pass {DROP_FLAG} to drop "
            f"such frames (the results row records how many)")


def drop_nonfinite(low: LowDim, cache: FeatureCache, *, drop: bool) -> tuple[LowDim, int]:
    """`low` without the frames whose state or action chunk hold a NaN/inf, and how many those were. Without
    `drop` any such frame is a FitError naming the cache, episode and frame: a NaN would flow into the
    normalisation, the loss and the MSE. (Caches extracted before stage 1 refused them, or with
    `extract --allow-nonfinite`, can hold them.) Features are checked block by block as they stream
    (graftcache.fit.stream), since they are never all in memory."""
    bad = low.nonfinite()
    any_bad = np.logical_or.reduce(list(bad.values()))
    if not any_bad.any():
        return low, 0
    if not drop:
        name = next(n for n, b in bad.items() if b.any())
        at = int(np.flatnonzero(bad[name])[0])
        raise FitError(nonfinite_message(cache, name, int(low.episode_index[at]), int(low.frame_index[at]),
                                         f"{int(any_bad.sum())} of {len(low)} frame(s) non-finite"))
    return low.take(np.flatnonzero(~any_bad)), int(any_bad.sum())
