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


#: Float dtype -> (unsigned view, exponent bits): a value is NaN or inf exactly when its bits without the sign
#: are at least its all-ones exponent.
_EXPONENT: dict[torch.dtype, tuple[type, int]] = {
    torch.float16: (np.uint16, 0x7C00), torch.bfloat16: (np.uint16, 0x7F80),
    torch.float32: (np.uint32, 0x7F800000), torch.float64: (np.uint64, 0x7FF0000000000000),
}
_SIGNED = {2: torch.int16, 4: torch.int32, 8: torch.int64}


def nonfinite_rows(values: np.ndarray | torch.Tensor) -> np.ndarray:
    """Bool [N]: rows of `values` ([N, ...], any float dtype incl. bf16 tensors) holding a NaN or an inf.

    Read from the bits (magnitude >= the all-ones exponent), not with `torch.isfinite`: on CPU that runs many
    times slower on fp16 tensors (docs/measured.md), and stage 2 checks every block of features it streams."""
    t = values if isinstance(values, torch.Tensor) else torch.from_numpy(np.ascontiguousarray(values))
    if not t.is_floating_point() or t.numel() == 0:
        return np.zeros(t.shape[0], dtype=bool)
    unsigned, exponent = _EXPONENT[t.dtype]
    bits = t.contiguous().view(_SIGNED[t.element_size()]).numpy().view(unsigned).reshape(t.shape[0], -1)
    magnitude = np.bitwise_and(bits, unsigned(np.iinfo(unsigned).max >> 1))
    return magnitude.max(axis=1) >= exponent


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
