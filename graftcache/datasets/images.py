"""Decode one episode's PNG frames stored inside a data parquet (struct<bytes, path> columns).

Used by image-mode datasets (HuggingFaceVLA/libero, physical-intelligence/libero, lerobot
`use_videos=False`). Rows are located through the `episode_index` column rather than trusted offsets,
and only the row groups that hold the episode are read, so a 100 MB v3 data file is not loaded whole.
PNG is lossless, so any correct decoder is bit-exact; PIL was the fastest measured here.
"""

from __future__ import annotations

import io
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
from PIL import Image

from graftcache.errors import DatasetError


def decode_rows(
    path: Path,
    episode: int,
    keys: Sequence[str],
    length: int,
    shapes: Sequence[tuple[int, int, int]],
) -> dict[str, np.ndarray]:
    """Feature key -> uint8 [length, H, W, 3] for the rows of `episode` in `path`, in frame order."""
    if not path.is_file():
        raise DatasetError(f"{path}: data file missing (episode {episode})")
    pf = pq.ParquetFile(path)
    missing = [k for k in keys if k not in pf.schema_arrow.names]
    if missing:
        raise DatasetError(f"{path}: no image column(s) {', '.join(missing)} (episode {episode})")
    table = _episode_rows(pf, path, episode, length, [*keys, "frame_index"])
    if table.column("frame_index").to_pylist() != list(range(length)):
        raise DatasetError(f"{path}: episode {episode} rows are not frames 0..{length - 1} in order")
    return {key: _decode_column(table.column(key), path, key, episode, shape) for key, shape in zip(keys, shapes)}


def _episode_rows(pf: pq.ParquetFile, path: Path, episode: int, length: int, columns: list[str]) -> pa.Table:
    """The `length` contiguous rows of `episode`, reading only the row groups that overlap them."""
    rows = np.flatnonzero(pf.read(columns=["episode_index"]).column(0).to_numpy() == episode)
    if rows.size != length:
        raise DatasetError(f"{path}: episode {episode} has {rows.size} rows, metadata says length {length}")
    if rows[-1] - rows[0] + 1 != length:
        raise DatasetError(f"{path}: episode {episode} rows are not contiguous")
    sizes = [pf.metadata.row_group(i).num_rows for i in range(pf.metadata.num_row_groups)]
    starts = np.concatenate([[0], np.cumsum(sizes)])
    groups = [i for i in range(len(sizes)) if starts[i] <= rows[-1] and starts[i + 1] > rows[0]]
    table = pf.read_row_groups(groups, columns=columns)
    return table.slice(int(rows[0] - starts[groups[0]]), length)


def _decode_column(column: pa.ChunkedArray, path: Path, key: str, episode: int,
                   shape: tuple[int, int, int]) -> np.ndarray:
    out = np.empty((len(column), *shape), dtype=np.uint8)
    cells = column.combine_chunks().field("bytes").to_pylist()
    for k, data in enumerate(cells):
        try:
            with Image.open(io.BytesIO(data)) as im:
                frame = np.asarray(im if im.mode == "RGB" else im.convert("RGB"))
        except (OSError, TypeError, ValueError) as e:
            raise DatasetError(f"{path}: {key} episode {episode} frame {k}: not a decodable image "
                               f"({type(e).__name__})") from None
        if frame.shape != shape:
            raise DatasetError(f"{path}: {key} episode {episode} frame {k} is {frame.shape}, "
                               f"info.json declares {shape}")
        out[k] = frame
    return out
