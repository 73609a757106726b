"""Rows of one run_id from two machines: equal, or within float32's last bits, they merge quietly; computed on other
kernels (the bf16 products of an AMX host against an AVX512-BF16 one), `graftcache merge-rows` says in one line
which run_ids differ, by how much and on which kernels, and keeps the last merged."""

from __future__ import annotations

from pathlib import Path

import pytest
from helpers.tables import row, table

from graftcache import results
from graftcache.cli import main
from graftcache.results.same_result import TOLERANCE, disagreement

AMX, AVX512_BF16 = "cpu:avx512+amx", "cpu:avx512+avx512_bf16"


def _row(seed: int, eval_mse: float, kernels: str | None, **over: object) -> dict:
    """The row of the cell of `seed` (its run_id the seed's, whatever computed it) as `kernels` computed it."""
    return row("smolvla", "libero_spatial", "siglip", seed, eval_mse, run_id=f"{seed:016x}", kernels=kernels,
               compute_dtype="bf16", **over)


def test_rows_of_one_run_id_agree_within_the_tolerance_and_differ_beyond_it() -> None:
    same = table([_row(0, 0.5, AMX), _row(0, 0.5, AMX), _row(1, 0.3, AMX)])
    assert disagreement(same) is None
    within = table([_row(0, 0.5, AMX), _row(0, 0.5 * (1 + TOLERANCE / 2), AVX512_BF16)])
    assert disagreement(within) is None
    nan = table([_row(0, float("nan"), AMX), _row(0, float("nan"), AMX)])
    assert disagreement(nan) is None
    apart = table([_row(0, 0.5, AMX), _row(0, 0.5044, AVX512_BF16), _row(1, 0.3, AMX),
                   _row(1, 0.3, AVX512_BF16, train_loss_final=0.25)])
    ids = apart["run_id"].unique(maintain_order=True).to_list()
    assert disagreement(apart) == (
        f"rows of 2 run_id(s) differ beyond the tolerance 1e-06 (relative): {ids[0]}: eval_mse 0.5 vs 0.5044 "
        f"({AMX} bf16 vs {AVX512_BF16} bf16); {ids[1]}: train_loss_final 0.5 vs 0.25 ({AMX} bf16 vs "
        f"{AVX512_BF16} bf16); rows of one run_id agree only where the same kernels and dtype computed them")
    older = table([_row(0, 0.5, AMX), _row(0, 0.6, None)])  # a row of format 6 or older: its kernels unknown
    assert "(cpu:avx512+amx bf16 vs kernels unknown bf16)" in disagreement(older)


def test_merge_rows_says_in_one_line_which_rows_of_a_run_id_differ(tmp_path: Path,
                                                                      capsys: pytest.CaptureFixture) -> None:
    ours, theirs, again = (tmp_path / f"{name}.parquet" for name in ("ours", "theirs", "again"))
    results.append(ours, table([_row(0, 0.5, AMX), _row(1, 0.3, AMX)]))
    results.append(theirs, table([_row(0, 0.5044, AVX512_BF16), _row(1, 0.3, AVX512_BF16)]))
    results.append(again, table([_row(1, 0.3, AMX)]))
    assert main(["merge-rows", str(again), "--results", str(ours)]) == 0
    assert "differ" not in capsys.readouterr().out
    assert main(["merge-rows", str(theirs), "--results", str(ours)]) == 0
    lines = capsys.readouterr().out.splitlines()
    run_id = results.read(theirs)["run_id"][0]
    differ = [line for line in lines if "differ beyond the tolerance" in line]
    assert len(differ) == 1 and differ[0].startswith(f"{ours}: rows of 1 run_id(s) differ")
    assert f"{run_id}: eval_mse 0.5 vs 0.5044 ({AMX} bf16 vs {AVX512_BF16} bf16)" in differ[0]
    assert differ[0].endswith("; the last merged is kept")
    merged = results.read(ours)
    assert merged.height == 2 and merged.filter(merged["run_id"] == run_id)["eval_mse"].to_list() == [0.5044]
