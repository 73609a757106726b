"""Finding NaN/inf in what a cache holds, by frame, so that no non-finite value reaches a normaliser or an MSE.

Stage 1 refuses them (a dataset's state/action columns before anything is encoded, features block by
block before the block is written) unless the user keeps them explicitly (`extract --allow-nonfinite`);
stage 2 refuses a cache that holds them unless `fit --drop-nonfinite` drops those frames.
"""

from __future__ import annotations

import numpy as np
import polars as pl
import torch

#: Flags named in the messages, defined once.
KEEP_FLAG = "--allow-nonfinite"
DROP_FLAG = "--drop-nonfinite"


def nonfinite_rows(values: np.ndarray | torch.Tensor) -> np.ndarray:
    """Bool [N]: rows of `values` ([N, ...], any float dtype incl. bf16 tensors) holding a NaN or an inf."""
    t = values if isinstance(values, torch.Tensor) else torch.from_numpy(np.ascontiguousarray(values))
    if not t.is_floating_point():
        return np.zeros(t.shape[0], dtype=bool)
    return (~torch.isfinite(t)).reshape(t.shape[0], -1).any(dim=1).numpy()


def lowdim_problem(table: pl.DataFrame, columns: tuple[str, ...] = ("state", "action")) -> str | None:
    """'episode E frame F: <column> is [...]' for the first frame of `table` (episode_index, frame_index and
    array columns) with a non-finite value, with the count of such frames; None when all are finite."""
    for name in columns:
        bad = nonfinite_rows(np.stack(table[name].to_numpy()) if table.height else np.zeros((0, 1), np.float32))
        if bad.any():
            row = table.row(int(np.flatnonzero(bad)[0]), named=True)
            values = np.asarray(row[name], dtype=np.float64)
            dim = int(np.flatnonzero(~np.isfinite(values))[0])
            return (f"episode {row['episode_index']} frame {row['frame_index']}: {name}[{dim}] is {values[dim]} "
                    f"({int(bad.sum())} frame(s) with NaN/inf in {name})")
    return None
