"""When two rows of one run_id are one result: a run's scores depend on its cell, its compute dtype and the kernels
that computed it (graftcache.runtime.kernels, the `kernels` column), not on the thread count or the process. Rows of
one run_id from other kernels (bf16 products on AMX tiles against those on AVX512-BF16, or emulated on AVX2) differ,
and a merge of such rows says so (`disagreement`) instead of replacing one with the other unremarked."""

from __future__ import annotations

import math

import polars as pl

#: How far apart, relative (|a - b| / max(|a|, |b|)), two rows of one run_id may score and still be one result. Rows
#: computed on equal kernels in one dtype are equal bit for bit, so this lets through float32's own last bits (the
#: rows of a graftcache whose sums depended on the thread count) and nothing that training and scoring on other
#: kernels move.
TOLERANCE = 1e-6
#: The scores of a row compared.
SCORES = ("eval_mse", "train_loss_final")


def _apart(a: float | None, b: float | None) -> bool:
    """Whether two values of a score differ beyond TOLERANCE (a missing value on either side is no disagreement; NaN
    against a number is one)."""
    if a is None or b is None or a == b or (math.isnan(a) and math.isnan(b)):
        return False
    return not abs(a - b) <= TOLERANCE * max(abs(a), abs(b))


def _computed(row: dict) -> str:
    return f"{row['kernels'] or 'kernels unknown'} {row['compute_dtype']}"


def disagreement(rows: pl.DataFrame) -> str | None:
    """One line naming each run_id of `rows` (in their order) whose rows differ in a score beyond TOLERANCE, with
    the first of its rows and the first that differs from it, each with its kernels and dtype; None where every
    run_id's rows agree."""
    found = []
    for run_id, group in rows.group_by("run_id", maintain_order=True):
        first, *rest = group.select("run_id", *SCORES, "kernels", "compute_dtype").iter_rows(named=True)
        for other in rest:
            apart = [s for s in SCORES if _apart(first[s], other[s])]
            if apart:
                scores = ", ".join(f"{s} {first[s]:.6g} vs {other[s]:.6g}" for s in apart)
                found.append(f"{run_id[0]}: {scores} ({_computed(first)} vs {_computed(other)})")
                break
    if not found:
        return None
    return (f"rows of {len(found)} run_id(s) differ beyond the tolerance {TOLERANCE:g} (relative): "
            f"{'; '.join(found)}; rows of one run_id agree only where the same kernels and dtype computed them")
