#!/usr/bin/env python
"""What one appended results row costs with N rows already in the file (graftcache.results.append: take the
writers' lease file, read the whole table, write it again to a temporary file, fsync, rename).

    python benchmarks/bench_results.py [--rows 10000] [--repeats 20] [--writers 4] [--folder DIR]

Prints the median time of one single-row append by one writer, its parts (read, write + fsync, the lease),
and the rows/s that `--writers` processes appending at once reach together. Rows are shaped like a fit's:
every SCHEMA column, 10 per-episode MSEs, a command line. `--folder` puts the file on another file system
(an NFS mount, to see what the shared case costs); by default a temporary folder.
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import machine, median_seconds  # noqa: E402

from graftcache import results  # noqa: E402
from graftcache.file_lease import FileLease  # noqa: E402
from graftcache.results import writing  # noqa: E402


def fit_row(i: int, writer: int = 0) -> dict:
    """A row as a fit writes it (values seeded by `i`), with its own run_id."""
    cell = {"encoder": f"enc{writer}", "seed": i, "control": "none"}
    return {
        "run_id": results.make_run_id(cell), "format_version": results.FORMAT_VERSION, "backbone": "smolvla",
        "policy": "lerobot/smolvla_base",
        "policy_sha256": "0" * 64, "encoder": cell["encoder"], "cache_key": "k" * 32, "suite": "libero_spatial",
        "seed": i, "control": "none", "pool_grid": "8x8", "objective": "flow", "steps": 300, "lr": 1e-3,
        "batch_size": 16, "buffer_mib": 2048, "train_loss_final": 0.5 + i * 1e-6, "eval_mse": 1.0 + i * 1e-6,
        "eval_mse_first": 0.9, "eval_mse_raw": 0.01, "eval_mse_arm": 1.0, "eval_mse_gripper": 1.0,
        "eval_split": "graftcache", "eval_mse_episodes": [1.0 + k / 10 for k in range(10)],
        "n_eval_frames": 1200, "n_eval_episodes": 10, "eval_split_seed": 0, "wall_s": 60.0, "device": "cuda",
        "compute_dtype": "bf16", "random_init": False, "n_dropped_nonfinite": 0, "numerics_drift": 0.0,
        "graftcache_version": "0.1.0",
        "command": "graftcache sweep cli/paper.toml --executor local --results results.parquet",
    }


def _writer(args: tuple[str, int, int]) -> tuple[float, float]:
    """`n` appends by one process; returns when its first began and its last ended (wall clock)."""
    path, writer, n = args
    t0 = time.time()
    for i in range(n):
        results.append(path, [fit_row(1_000_000 + i, writer)])
    return t0, time.time()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", type=int, default=10_000)
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--writers", type=int, default=4)
    ap.add_argument("--folder", type=Path, default=None)
    args = ap.parse_args()
    lscpu = subprocess.run(["lscpu"], capture_output=True, text=True).stdout
    print("lscpu model:", next((ln.split(":", 1)[1].strip() for ln in lscpu.splitlines()
                                if ln.startswith("Model name")), "?"))
    print(machine())
    with tempfile.TemporaryDirectory(dir=args.folder) as tmp:
        path = Path(tmp) / "results.parquet"
        results.validate(results.from_rows(fit_row(i) for i in range(args.rows))).write_parquet(path)
        print(f"{args.rows} rows, {path.stat().st_size / 2**20:.2f} MiB on disk")
        count = iter(range(args.rows, 10**9))
        append = median_seconds(lambda: results.append(path, [fit_row(next(count))]), args.repeats)
        read = median_seconds(lambda: results.read(path), args.repeats)
        table = results.read(path)
        held = FileLease(writing.lock_path(path))
        assert held.try_acquire()
        write = median_seconds(lambda: writing._publish(path, table, held), args.repeats)
        held.release()

        def lease() -> None:
            with FileLease(writing.lock_path(path)):
                pass

        take = median_seconds(lease, args.repeats)
        print(f"one append (1 row): {append * 1e3:.1f} ms median of {args.repeats}; of which read {read * 1e3:.1f} ms, "
              f"write + fsync + rename {write * 1e3:.1f} ms, lease take + give back {take * 1e3:.2f} ms")
        n = args.repeats
        with mp.get_context("spawn").Pool(args.writers) as workers:
            spans = workers.map(_writer, [(str(path), w, n) for w in range(1, args.writers + 1)])
        wall = max(end for _, end in spans) - min(start for start, _ in spans)
        rows = results.read(path).height
        expected = args.rows + 1 + args.repeats + args.writers * n  # + median_seconds' warm-up append
        print(f"{args.writers} writers x {n} appends at once: {args.writers * n / wall:.1f} rows/s together "
              f"({wall:.1f} s from the first append to the last); rows {rows}, expected {expected}")
        assert rows == expected, "rows lost"


if __name__ == "__main__":
    main()
