#!/usr/bin/env python
"""The closed-loop benchmarks' cells, fitted and exported once: a plain graft of a random-init ViT-Ti/16 and its
zero-image control on a 1-step tiny SmolVLA, fit on the bundled sample's first libero_object task (the CI smoke's
cells, tests/fixtures/simulator_cells.py). benchmarks/bench_rollout.py fits them where it runs; gpu_check's
closed-loop stage takes them ready-made (`--closed-loop-cells`), so that a lent GPU machine, whose image lacks the
data layer's packages, only rolls them out.

    python benchmarks/closed_loop_cells.py FOLDER     # FOLDER/{results.parquet, cache/, exports/RUN_ID/}
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "data" / "libero_sample"
ENCODER = "timm:vit_tiny_patch16_224"
SUITE, TASK = "libero_object", 0  # the sample's first libero_object task: its episodes 18-21
RESULTS, CACHE, EXPORTS = "results.parquet", "cache", "exports"


def graftcache(*argv: object) -> None:
    """One graftcache command in a fresh process, offline; its error output ends this script."""
    done = subprocess.run([sys.executable, "-m", "graftcache", *map(str, argv)],
                          env={**os.environ, "HF_HUB_OFFLINE": "1"}, capture_output=True, text=True)
    if done.returncode:
        sys.exit(f"graftcache {argv[0]} failed:\n{done.stderr[-3000:]}")


def fit_cells(folder: Path) -> tuple[Path, Path]:
    """The two cells fitted into `folder`: its results file and cache root."""
    cache, policy, results = folder / CACHE, folder / "policy", folder / RESULTS
    graftcache("train-tiny", "--backbone", "smolvla", "--dataset", SAMPLE, "--steps", 1, "--out", policy,
               "--cache", cache)
    graftcache("extract", "--encoder", ENCODER, "--random-init", "--dataset", SAMPLE, "--episodes", "18-21",
               "--frame-stride", 8, "--num-workers", 0, "--batch-size", 16, "--no-progress", "--cache", cache)
    graftcache("fit", "--backbone", "smolvla", "--policy", policy, "--encoder", ENCODER, "--dataset", SAMPLE,
               "--suite", SUITE, "--seeds", 1, "--controls", "zero-image", "--steps", 2, "--batch-size", 4,
               "--eval-fraction", 0.5, "--eval-frames", 4, "--num-denoise-steps", 2, "--cache", cache, "--results",
               results, "--no-progress")
    return results, cache


def export_cells(results: Path, cache: Path, exports: Path) -> list[str]:
    """Every libero_object cell of `results` exported to `exports`/RUN_ID (where a rollout beside it looks first);
    their run_ids."""
    import polars as pl

    cells = pl.read_parquet(results).filter(pl.col("suite") == SUITE)["run_id"].to_list()
    for run_id in cells:
        graftcache("export", run_id, "--results", results, "--out", exports / run_id, "--cache", cache)
    return cells


def prepared(cells: Path, folder: Path) -> Path:
    """A rollouts file in `folder`, the cells' exports (where they have them) copied beside it, where a rollout
    looks first: no measured run pays for an export."""
    if (cells / EXPORTS).is_dir():
        shutil.copytree(cells / EXPORTS, folder / EXPORTS)
    return folder / "rollouts.parquet"


def rollout_argv(cells: Path, rollouts: Path, *, episodes: int, steps: int, workers: int,
                 flags: tuple[object, ...] = ()) -> list[str]:
    """`graftcache rollout` of the cells on their task into `rollouts` (made by `prepared`), with `flags` added."""
    return [str(a) for a in (sys.executable, "-m", "graftcache", "rollout", cells / RESULTS, "--cache", cells / CACHE,
                             "--rollouts", rollouts, "--suites", SUITE, "--tasks", TASK, "--episodes-per-task",
                             episodes, "--max-steps", steps, "--workers", workers, *flags)]


def main(argv: list[str] | None = None) -> None:
    (folder,) = argv if argv is not None else sys.argv[1:] or [""]
    if not folder:
        sys.exit(__doc__.strip().splitlines()[-1].strip())
    folder = Path(folder)
    if (folder / RESULTS).exists():
        sys.exit(f"{folder / RESULTS}: exists; pass an empty or new folder")
    results, cache = fit_cells(folder)
    cells = export_cells(results, cache, folder / EXPORTS)
    print(f"{len(cells)} cells fitted and exported into {folder}: {', '.join(cells)}")


if __name__ == "__main__":
    main()
