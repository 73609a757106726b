#!/usr/bin/env python
"""The closed-loop bundle checked here on CPU: rollouts from .whl/closed_loop.tar.xz's packages and trimmed data, on
a Python that sees only what the device will have, give the rows the full install gives.

    python benchmarks/device/check_closed_loop_bundle.py     # after bundle_closed_loop.sh

The bundle is unpacked into a temporary folder; its compiled packages (built for the device's CPython 3.12) are
dropped, so this .venv's Python runs its pure-Python ones (robosuite, hf-libero, bddl, PyOpenGL, polars' front end,
zarr...) with the data trimmed to benchmarks/device/closed_loop_files.txt, hf-libero's config pointing at it, and its
cells (relocated, their cache trimmed). That Python runs without its site-packages (`-S`, which spawned workers
inherit); in their place a folder of links to the .venv's distributions that the device has: the image's
(benchmarks/device/image_packages.txt), bundle A's and this bundle's (as benchmarks/device/bundle.sh and
bundle_closed_loop.sh name them), so an import the device could not satisfy fails here too, and one that is optional
(timm's wandb, accelerate's boto3) takes its absent path. Each rollout (one cell, 2 episodes of 5 steps; soft resets
in-process, then a perturbation on 2 workers) is run once so and once on the full install, and their rows must be
equal but for `seconds` and `command`. What it cannot check: the image's own versions of its packages, the cp312
builds, and EGL on an NVIDIA driver (run_closed_loop.sh's smoke does).
"""

from __future__ import annotations

import importlib.metadata
import os
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path

import trace_closed_loop_files as tracing
from closed_loop_cells import SUITE, prepared

HERE, ROOT = tracing.HERE, tracing.ROOT
BUNDLE = ROOT / ".whl" / "closed_loop.tar.xz"
#: the rollouts compared: (reset, workers, perturbation in cm)
RUNS = (("soft", 1, 0), ("hard", 2, 3))
#: columns that differ between two runs of the same episodes
UNCOMPARED = ("seconds", "command")
LIBERO_KEYS = {"benchmark_root": "", "bddl_files": "bddl_files", "init_states": "init_files",
               "datasets": "../datasets", "assets": "assets"}


def unpacked(folder: Path) -> Path:
    """The bundle unpacked into `folder`, its compiled distributions removed; its site folder."""
    with tarfile.open(BUNDLE) as tar:
        tar.extractall(folder, filter="fully_trusted")
    site = folder / "site"
    for record in site.glob("*.dist-info/RECORD"):
        files = [line.split(",")[0] for line in record.read_text().splitlines()]
        if any(".so" in Path(f).name for f in files):
            for f in files:
                (site / f).unlink(missing_ok=True)
    return site


def libero_config(site: Path, folder: Path) -> Path:
    """A LIBERO_CONFIG_PATH whose config.yaml points hf-libero at the unpacked data, as run_closed_loop.sh writes."""
    benchmark = site / "libero" / "libero"
    folder.mkdir()
    (folder / "config.yaml").write_text("".join(f"{key}: {os.path.normpath(benchmark / rel)}\n"
                                                for key, rel in LIBERO_KEYS.items()))
    return folder


def device_distributions() -> set[str]:
    """The distributions the device has: the image's, bundle A's and the closed-loop bundle's."""
    bundles = tracing.shell_packages(HERE / "bundle.sh") | tracing.shell_packages(HERE / "bundle_closed_loop.sh")
    return tracing.image_packages() | bundles


def shadow_site(folder: Path, allowed: set[str]) -> tuple[Path, list[str]]:
    """A folder of links to the top-level files and folders of this .venv's `allowed` distributions (their
    dist-info too); and the distributions left out."""
    folder.mkdir()
    left_out = []
    for dist in importlib.metadata.distributions():
        name = tracing.normalised(dist.metadata["Name"])
        if name not in allowed:
            left_out.append(name)
            continue
        base = Path(dist.locate_file(""))
        for top in {Path(f).parts[0] for f in dist.files or () if not str(f).startswith("..")}:
            link = folder / top
            if not link.exists() and (base / top).exists():
                link.symlink_to(base / top)
    return folder, sorted(left_out)


def rows(rollouts: Path):
    import polars as pl

    return pl.read_parquet(rollouts).drop(UNCOMPARED).sort("episode_id")


def rolled_out(cells: Path, folder: Path, reset: str, workers: int, perturb_cm: float, run_id: str,
               python: list[str], env: dict[str, str]) -> Path:
    """One rollout of `run_id` into `folder`; its rollouts file."""
    folder.mkdir()
    rollouts = prepared(cells, folder)
    command = tracing.rollout_command(cells, rollouts, reset, workers, perturb_cm, run_ids=[run_id])
    done = subprocess.run([*python, *command[1:]], cwd=ROOT, env=env, capture_output=True, text=True)
    if done.returncode:
        sys.exit(f"check: rollout in {folder.name} failed:\n{done.stderr[-3000:]}")
    return rollouts


def main() -> None:
    import polars as pl

    if not BUNDLE.is_file():
        sys.exit(f"check: {BUNDLE} is missing; run benchmarks/device/bundle_closed_loop.sh first")
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        site = unpacked(work / "bundle")
        cells = work / "bundle" / "closed_loop" / "cells"
        origin = Path((work / "bundle" / "closed_loop" / "cells.origin").read_text().strip())
        shadow, left_out = shadow_site(work / "shadow", device_distributions())
        run_id = pl.read_parquet(origin / "results.parquet").filter(
            (pl.col("suite") == SUITE) & (pl.col("control") == "none"))["run_id"][0]
        base = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "LIBERO_CONFIG_PATH")}
        full_env = {**base, "PYTHONPATH": str(ROOT), "HF_HUB_OFFLINE": "1"}
        device_env = {**base, "PYTHONPATH": f"{site}:{ROOT}:{shadow}", "HF_HUB_OFFLINE": "1",
                      "LIBERO_CONFIG_PATH": str(libero_config(site, work / "libero"))}
        where = subprocess.run([sys.executable, "-S", "-c", "import robosuite.macros, libero.libero, mujoco, polars; "
                                "print(robosuite.macros.__file__, libero.libero.__file__)"],
                               env=device_env, capture_output=True, text=True)
        if where.returncode or any(not p.startswith(str(site)) for p in where.stdout.split()):
            sys.exit(f"check: the simulator does not import from the unpacked bundle:\n{where.stdout}{where.stderr}")
        print(f"check: {len(left_out)} .venv distributions hidden (not on the device), e.g. "
              f"{' '.join(n for n in left_out if n in ('wandb', 'boto3', 'pydantic', 'cffi', 'platformdirs'))}")
        for reset, workers, perturb_cm in RUNS:
            name = f"{reset}-{workers}-{perturb_cm}"
            full = rows(rolled_out(origin, work / f"full-{name}", reset, workers, perturb_cm, run_id,
                                   [sys.executable], full_env))
            device = rows(rolled_out(cells, work / f"device-{name}", reset, workers, perturb_cm, run_id,
                                     [sys.executable, "-S"], device_env))
            if not full.equals(device):
                sys.exit(f"check: {name}: the bundle's rows differ from the full install's:\n{full}\n{device}")
            print(f"check: {reset} reset, {workers} worker(s), perturbation {perturb_cm} cm: {full.height} rows "
                  f"of run {run_id} equal to the full install's (success {full['success'].to_list()}, min target "
                  f"distance {[round(x, 4) for x in full['min_target_distance_m']]} m)")


if __name__ == "__main__":
    main()
