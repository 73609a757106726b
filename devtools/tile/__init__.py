"""Bigger LeRobot v3.0 datasets made of a small one's frames, without encoding a single frame.

Why: scale work (extraction memory, sharded extraction, the LIBERO-sized benchmark) needs LIBERO's real
dimensions (1,693 episodes, 273,465 frames of two 256x256 AV1 cameras), but the real data is not on every
machine and encoding that many frames takes hours. A v3.0 episode is only a pointer into a concatenated
mp4 (chunk/file index, from_timestamp, to_timestamp), so a new episode can be any window of consecutive
frames inside one of the source's video files. `tile` links the source's mp4s into the new dataset and
writes metadata and low-dim rows only: each window's rows are the source rows of the same frames, so
images, state and action stay consistent. Tasks are real LIBERO instructions (or the source's own), so
`graftcache.datasets.suite_of` gives every episode the suite it was built for; the frames are the
source's scenes, whatever the instruction says, so a tiled dataset is for measuring, not for fitting.

A developer tool, not library code (benchmarks and tests build datasets with it): the command is
`python -m devtools.tile SOURCE DEST (--preset libero | --episodes N) [--frames M] [--seed S]`
(devtools/tile/cli.py), its flags built from TileRequest's `setting(...)` declarations as graftcache's own are.
"""

from __future__ import annotations

import json
import os
import shutil
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import polars as pl
import pyarrow as pa
import pyarrow.parquet as pq

from devtools.libero_counts import LIBERO_COUNTS
from graftcache.checks import POSITIVE, SEED
from graftcache.datasets.meta import DatasetMeta
from graftcache.datasets.source import open_dataset
from graftcache.datasets.suites import suite_tasks
from graftcache.errors import DatasetError, GraftcacheError
from graftcache.settings import Checked, setting

#: Episode lengths are drawn uniformly within this factor of their part's mean length (then made to add up).
LENGTH_SPREAD = 0.3
#: Provenance of a tiled dataset, at its root (outside meta/, so not part of its identity).
RECORD = "tile.json"
_QUANTILES = {"q01": 0.01, "q10": 0.10, "q50": 0.50, "q90": 0.90, "q99": 0.99}
_DATA_FILE = "data/chunk-000/file-000.parquet"
_EPISODES_FILE = "meta/episodes/chunk-000/file-000.parquet"


@dataclass(frozen=True)
class TileRequest(Checked):
    """What `python -m devtools.tile` builds: a dataset of `preset`'s dimensions, or of `episodes` episodes (and
    `frames` frames; default: the source's mean length times `episodes`) over the source's tasks."""

    source: str = setting(positional=True,
                          help="v3.0 dataset with video cameras (folder or hub repo id in the local HF cache)")
    dest: str = setting(positional=True, help="new dataset folder (must not exist)")
    preset: str | None = setting(None, help="libero: 1,693 episodes, 273,465 frames in 4 suites")
    episodes: int | None = setting(None, rule=POSITIVE, metavar="N",
                                   help="N episodes over SOURCE's tasks (N = k x SOURCE's episodes for k times SOURCE)")
    frames: int | None = setting(None, rule=POSITIVE, metavar="M",
                                 help="frames in all, with --episodes (default: SOURCE's mean episode length x N)")
    seed: int = setting(0, rule=SEED, help="seed of episode lengths and window positions")

    def __post_init__(self) -> None:
        super().__post_init__()
        if (self.preset is None) == (self.episodes is None):
            raise GraftcacheError("tile needs exactly one of preset and episodes")
        if self.frames is not None and self.episodes is None:
            raise GraftcacheError("frames goes with episodes (a preset fixes its own frame counts)")


@dataclass(frozen=True)
class TilePart:
    """`episodes` new episodes of `frames` frames in all; their tasks are `tasks` in contiguous blocks."""

    tasks: tuple[str, ...]
    episodes: int
    frames: int


@dataclass(frozen=True)
class Window:
    """One new episode: its task and the source frames it shows, by position in the source's dataset order."""

    task: str
    start: int
    length: int


@dataclass(frozen=True)
class _Episodes:
    """The source's episodes in dataset order: where each starts (position) and, per camera key, its mp4
    (chunk, file) and from_timestamp; `run` numbers the stretches of consecutive episodes whose frames
    follow each other in the same mp4 of every camera (a window may cross episodes only inside a run)."""

    position: np.ndarray
    length: np.ndarray
    run: np.ndarray
    videos: dict[str, pl.DataFrame]  # key -> columns chunk_index, file_index, from_timestamp


def libero_parts(meta: DatasetMeta) -> tuple[TilePart, ...]:
    """lerobot/libero's dimensions: the four evaluation suites with their real counts and instructions."""
    table = suite_tasks()
    return tuple(TilePart(table[suite], n, frames) for suite, (n, frames) in LIBERO_COUNTS.items())


def scaled_parts(meta: DatasetMeta, episodes: int, frames: int | None = None) -> tuple[TilePart, ...]:
    """`episodes` episodes over the source's own tasks; `frames` defaults to the source's mean length times
    `episodes` (so k times the source's episode count is k times its frames)."""
    if frames is None:
        frames = round(episodes * meta.n_frames / len(meta.episodes))
    return (TilePart(meta.tasks, episodes, frames),)


#: --preset name -> the parts it builds from a source's metadata.
PRESETS: dict[str, Callable[[DatasetMeta], tuple[TilePart, ...]]] = {"libero": libero_parts}


def tile(request: TileRequest) -> Path:
    """Write the dataset `request` describes to `request.dest` (which must not exist) from windows of
    `request.source` (a v3.0 dataset with video cameras), and return its path.

    Episode lengths and window positions are drawn from `request.seed`; the totals per part are exact. The
    folder is built beside the destination and renamed into place last, so it never holds half a dataset.
    """
    dest = Path(request.dest)
    if dest.exists():
        raise DatasetError(f"{dest}: already exists; tile writes a new dataset folder")
    meta = open_dataset(request.source).meta
    if meta.codebase_version != "v3.0" or set(meta.camera_storage.values()) != {"video"}:
        raise DatasetError(f"{meta.root}: tile needs a v3.0 dataset whose cameras are all videos "
                           f"(found {meta.codebase_version}, storage {meta.camera_storage})")
    parts = parts_of(request, meta)
    source_eps = _source_episodes(meta)
    windows = _draw_windows(parts, source_eps, np.random.default_rng(request.seed), meta.root)
    partial = dest.with_name(f".{dest.name}.partial")
    shutil.rmtree(partial, ignore_errors=True)
    partial.mkdir(parents=True)
    try:
        tasks = tuple(dict.fromkeys(t for part in parts for t in part.tasks))
        info = json.loads((meta.root / "meta" / "info.json").read_text())
        table = _write_data(partial, meta, windows, tasks, info["fps"])
        _write_episodes(partial, meta, source_eps, windows)
        _write_tasks(partial, tasks)
        _write_info(partial, info, len(windows), sum(w.length for w in windows), len(tasks))
        _write_stats(partial, meta, table)
        _link_videos(partial, meta)
        (partial / RECORD).write_text(json.dumps({
            "source": str(meta.root.resolve()), "seed": request.seed,
            "parts": [{"tasks": len(p.tasks), "episodes": p.episodes, "frames": p.frames} for p in parts],
            "note": "episodes are windows of the source's frames; videos are links to the source's files",
        }, indent=2) + "\n")
    except BaseException:
        shutil.rmtree(partial, ignore_errors=True)
        raise
    os.rename(partial, dest)
    return dest


def parts_of(request: TileRequest, meta: DatasetMeta) -> tuple[TilePart, ...]:
    """The parts a request asks for: its preset's, or `scaled_parts` (a TileRequest sets exactly one)."""
    if request.preset is not None:
        if request.preset not in PRESETS:
            raise DatasetError(f"no tile preset {request.preset!r}; presets: {', '.join(PRESETS)}")
        return PRESETS[request.preset](meta)
    return scaled_parts(meta, request.episodes, request.frames)


def _draw_windows(parts: Sequence[TilePart], source_eps: _Episodes, rng: np.random.Generator,
                 root: Path) -> tuple[Window, ...]:
    """Every new episode's task, length and source window, part by part, in episode order."""
    runs = [(int(source_eps.position[source_eps.run == r][0]),
             int(source_eps.length[source_eps.run == r].sum())) for r in np.unique(source_eps.run)]
    longest = max(length for _, length in runs)
    windows = []
    for part in parts:
        lengths = _lengths(part, rng)
        if lengths.max() > longest:
            raise DatasetError(f"{root}: an episode of {int(lengths.max())} frames ({part.frames} frames over "
                               f"{part.episodes} episodes) does not fit in the source's longest stretch of "
                               f"consecutive frames in one video file ({longest} frames)")
        for j, length in enumerate(lengths.tolist()):
            slack = np.array([max(0, n - length + 1) for _, n in runs], dtype=np.float64)
            run = int(rng.choice(len(runs), p=slack / slack.sum()))
            start = runs[run][0] + int(rng.integers(0, slack[run]))
            windows.append(Window(part.tasks[j * len(part.tasks) // part.episodes], start, length))
    return tuple(windows)


def _lengths(part: TilePart, rng: np.random.Generator) -> np.ndarray:
    """`part.episodes` lengths >= 1 around the mean, adding up to exactly `part.frames` (largest remainder)."""
    if part.episodes < 1 or part.frames < part.episodes:
        raise DatasetError(f"cannot tile {part.frames} frames into {part.episodes} episodes "
                           "(every episode needs at least one frame)")
    weights = rng.uniform(1 - LENGTH_SPREAD, 1 + LENGTH_SPREAD, part.episodes)
    exact = part.frames * weights / weights.sum()
    lengths = np.maximum(np.floor(exact).astype(np.int64), 1)
    short = part.frames - int(lengths.sum())
    order = np.argsort(-(exact - lengths), kind="stable") if short > 0 else np.argsort(-lengths, kind="stable")
    for i in order[:abs(short)]:
        lengths[i] += 1 if short > 0 else -1
    return lengths


def _source_episodes(meta: DatasetMeta) -> _Episodes:
    """The source's episode rows (read straight from meta/episodes), in dataset order, split into runs."""
    keys = [meta.camera_keys[c] for c in meta.cameras]
    columns = ["episode_index", "length"] + [f"videos/{k}/{c}" for k in keys
                                             for c in ("chunk_index", "file_index", "from_timestamp")]
    files = sorted((meta.root / "meta" / "episodes").glob("chunk-*/file-*.parquet"))
    rows = pl.concat([pl.read_parquet(f, columns=columns) for f in files]).sort("episode_index")
    length = rows["length"].to_numpy().astype(np.int64)
    position = np.concatenate([[0], np.cumsum(length)[:-1]])
    columns = ("chunk_index", "file_index", "from_timestamp")
    videos = {k: rows.select(pl.col(f"videos/{k}/{c}").alias(c) for c in columns) for k in keys}
    breaks = np.zeros(len(length), dtype=bool)
    breaks[0] = True
    for v in videos.values():
        same_file = (v["chunk_index"].to_numpy()[1:] == v["chunk_index"].to_numpy()[:-1]) & \
                    (v["file_index"].to_numpy()[1:] == v["file_index"].to_numpy()[:-1])
        ts = v["from_timestamp"].to_numpy()
        follows = np.abs(ts[1:] - (ts[:-1] + length[:-1] / meta.fps)) < 0.5 / meta.fps
        breaks[1:] |= ~(same_file & follows)
    return _Episodes(position=position, length=length, run=np.cumsum(breaks) - 1, videos=videos)


def _write_data(root: Path, meta: DatasetMeta, windows: Sequence[Window], tasks: Sequence[str],
                fps: float) -> pa.Table:
    """Each window's source rows (all columns, the source's schema and its Hugging Face metadata), renumbered
    as the new episodes: episode_index, frame_index, index, timestamp and task_index."""
    paths = list(dict.fromkeys(p for p in meta.identity_files if p.suffix == ".parquet"
                               and p.is_relative_to(meta.root / "data")))
    schema = pq.read_schema(paths[0])
    source = pa.concat_tables([pq.read_table(p, schema=schema) for p in paths]) \
        .sort_by([("episode_index", "ascending"), ("frame_index", "ascending")])
    if source.num_rows != meta.n_frames:
        raise DatasetError(f"{meta.root}: the data files hold {source.num_rows} rows, the episodes "
                           f"{meta.n_frames} frames")
    lengths = np.array([w.length for w in windows], dtype=np.int64)
    first = np.repeat(np.concatenate([[0], np.cumsum(lengths)[:-1]]), lengths)
    index = np.arange(int(lengths.sum()), dtype=np.int64)
    frame = index - first
    task_of = {t: i for i, t in enumerate(tasks)}
    new = {
        "episode_index": np.repeat(np.arange(len(windows)), lengths),
        "frame_index": frame,
        "index": index,
        "timestamp": frame / fps,
        "task_index": np.repeat([task_of[w.task] for w in windows], lengths),
    }
    table = source.take(np.concatenate([np.arange(w.start, w.start + w.length) for w in windows]))
    for name, values in new.items():
        i = schema.get_field_index(name)
        table = table.set_column(i, schema.field(i), pa.array(values).cast(schema.field(i).type))
    path = root / _DATA_FILE
    path.parent.mkdir(parents=True)
    pq.write_table(table, path)
    return table


def _write_episodes(root: Path, meta: DatasetMeta, source_eps: _Episodes, windows: Sequence[Window]) -> None:
    """meta/episodes: one row per window, its video spans pointing into the source's mp4s."""
    lengths = np.array([w.length for w in windows], dtype=np.int64)
    starts = np.array([w.start for w in windows], dtype=np.int64)
    to_index = np.cumsum(lengths)
    at = np.searchsorted(source_eps.position, starts, side="right") - 1
    columns: dict[str, Any] = {
        "episode_index": np.arange(len(windows)),
        "tasks": [[w.task] for w in windows],
        "length": lengths,
        "data/chunk_index": np.zeros(len(windows), dtype=np.int64),
        "data/file_index": np.zeros(len(windows), dtype=np.int64),
        "dataset_from_index": to_index - lengths,
        "dataset_to_index": to_index,
    }
    for key, spans in source_eps.videos.items():
        from_ts = spans["from_timestamp"].to_numpy()[at] + (starts - source_eps.position[at]) / meta.fps
        columns[f"videos/{key}/chunk_index"] = spans["chunk_index"].to_numpy()[at]
        columns[f"videos/{key}/file_index"] = spans["file_index"].to_numpy()[at]
        columns[f"videos/{key}/from_timestamp"] = from_ts
        columns[f"videos/{key}/to_timestamp"] = from_ts + lengths / meta.fps
    columns["meta/episodes/chunk_index"] = np.zeros(len(windows), dtype=np.int64)
    columns["meta/episodes/file_index"] = np.zeros(len(windows), dtype=np.int64)
    path = root / _EPISODES_FILE
    path.parent.mkdir(parents=True)
    pq.write_table(pa.table({k: pa.array(v) for k, v in columns.items()}), path)


def _write_tasks(root: Path, tasks: Sequence[str]) -> None:
    """pandas, as lerobot writes it: lerobot reads tasks.parquet with pandas and looks tasks up by its index."""
    pd.DataFrame({"task_index": np.arange(len(tasks))}, index=pd.Index(list(tasks))).to_parquet(
        root / "meta" / "tasks.parquet")


def _write_info(root: Path, info: dict[str, Any], episodes: int, frames: int, tasks: int) -> None:
    """The source's info.json (features, fps, path templates) with the new totals."""
    info = {**info, "total_episodes": episodes, "total_frames": frames, "total_tasks": tasks,
            "splits": {"train": f"0:{episodes}"}}
    (root / "meta" / "info.json").write_text(json.dumps(info, indent=4) + "\n")


def _write_stats(root: Path, meta: DatasetMeta, table: pa.Table) -> None:
    """stats.json: every non-camera feature computed over the new rows; the cameras' statistics are the
    source's (the windows show the source's frames; recomputing them would mean decoding every frame)."""
    stats = json.loads((meta.root / "meta" / "stats.json").read_text())
    for name in table.column_names:
        if name in meta.camera_keys.values():
            continue
        column = table.column(name).combine_chunks()
        flat = column.flatten() if pa.types.is_fixed_size_list(column.type) else column
        stats[name] = _feature_stats(flat.to_numpy(zero_copy_only=False).reshape(len(column), -1))
    (root / "meta" / "stats.json").write_text(json.dumps(stats, indent=4) + "\n")


def _feature_stats(values: np.ndarray) -> dict[str, list]:
    """lerobot's per-feature statistics over rows [n, d]: min, max, mean, std, count and quantiles."""
    as_float = values.astype(np.float64)
    out = {"min": values.min(axis=0).tolist(), "max": values.max(axis=0).tolist(),
           "mean": as_float.mean(axis=0).tolist(), "std": as_float.std(axis=0).tolist(), "count": [len(values)]}
    return {**out, **{name: np.quantile(as_float, q, axis=0).tolist() for name, q in _QUANTILES.items()}}


def _link_videos(root: Path, meta: DatasetMeta) -> None:
    """Every mp4 of the source, linked at the same relative path (symbolic links to the resolved file, so
    nothing is copied and the hash memo of graftcache/datasets/identity.py, keyed by resolved path, applies)."""
    for path in meta.identity_files:
        if path.suffix == ".mp4":
            link = root / path.relative_to(meta.root)
            link.parent.mkdir(parents=True, exist_ok=True)
            link.symlink_to(path.resolve())
