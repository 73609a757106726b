#!/usr/bin/env python
"""Which simulator data files a closed-loop rollout opens, found by tracing one: the list
benchmarks/device/bundle_closed_loop.sh trims robosuite's and hf-libero's data to, so that the simulator fits a
lent GPU machine's carry (robosuite alone installs hundreds of MB of robot meshes a Panda rollout never reads).

    python benchmarks/device/trace_closed_loop_files.py CELLS    # CELLS: benchmarks/closed_loop_cells.py's folder

Rolls the cells out under `strace -f -e trace=open,openat` twice, as gpu_check's closed-loop stage does (libero_object
task 0, 2 episodes of 5 steps): soft resets in this process, then hard resets with a perturbation on 2 worker
processes (spawned: `-f` follows them). Every regular file under the simulator's packages (PACKAGES) that a process
opened, other than Python source, bytecode, extensions and caches (numba's, beside robosuite's modules), is written
to LIST relative to the folder holding the packages (`robosuite/models/assets/base.xml`); hf-libero's assets folder
may be a link elsewhere (scripts/setup.sh libero keeps it in the cache root), and is written as where it is linked
from. Rerun after a version bump of
robosuite, hf-libero or lerobot, or a change of the stage's suite or task; tests/test_device_bundle.py checks each
listed file is still installed.

It also prints the distributions whose modules the rollouts imported that neither the device image
(IMAGE_PACKAGES) nor bundle A (benchmarks/device/bundle.sh) holds: what bundle_closed_loop.sh must carry, plus the
ones imported only where present (timm's optional wandb, say), which benchmarks/device/check_closed_loop_bundle.py
shows the rollout runs without.
"""

from __future__ import annotations

import importlib.metadata
import importlib.util
import os
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]
sys.path.insert(0, str(HERE.parent))  # benchmarks/: the cells and their rollout

from closed_loop_cells import prepared, rollout_argv  # noqa: E402

LIST = HERE / "closed_loop_files.txt"
#: the device image's Python packages, as KINDS.md of the device tool lists them (benchmarks/device/README.md)
IMAGE_PACKAGES = HERE / "image_packages.txt"
#: the simulator's packages whose data files are traced (bddl ships none a rollout reads, but is checked)
PACKAGES = ("robosuite", "libero", "bddl")
#: the rollouts traced: (reset, workers, perturbation in cm)
RUNS = (("soft", 1, 0), ("hard", 2, 3))
#: each rollout's length: short episodes of the cells' task (gpu_check's closed-loop stage's)
EPISODES, STEPS = 2, 5
CODE_SUFFIXES = (".py", ".pyc", ".so")
#: an open or openat call's path, in a line of `strace -f` (which starts with the pid)
CALL = re.compile(r'^(\d+)\s+open(?:at)?\((?:[^,"]*, )?"([^"]*)"')
#: a call's successful result (a file descriptor), at the end of its line or of its resumed line
OPENED = re.compile(r"\)\s*=\s*\d+(?: <[^>]*>)?$")


def rollout_command(cells: Path, rollouts: Path, reset: str, workers: int, perturb_cm: float,
                    run_ids: list[str] | None = None) -> list[str]:
    """One of RUNS: `graftcache rollout` of `cells` into `rollouts` (closed_loop_cells.prepared)."""
    return rollout_argv(cells, rollouts, episodes=EPISODES, steps=STEPS, workers=workers,
                        flags=("--reset", reset, "--perturb-cm", perturb_cm,
                               *(["--run-ids", ",".join(run_ids)] if run_ids else [])))


def package_roots() -> dict[str, Path]:
    """Each traced package's folder, by the name its paths start with (the folder holding them is their root)."""
    roots = {}
    for name in PACKAGES:
        spec = importlib.util.find_spec(name)
        if spec is None or not spec.submodule_search_locations:
            sys.exit(f"trace: package {name} is not installed (make setup-libero)")
        roots[name] = Path(next(iter(spec.submodule_search_locations)))
    return roots


def aliases(roots: dict[str, Path]) -> list[tuple[str, str]]:
    """(real path prefix, listed prefix) pairs, longest first: each package folder as given and as resolved, and
    each link inside one (hf-libero's assets) as resolved."""
    pairs = []
    for name, folder in roots.items():
        pairs += [(str(folder), name), (str(folder.resolve()), name)]
        for dirpath, dirnames, _ in os.walk(folder):
            for d in dirnames:
                link = Path(dirpath, d)
                if link.is_symlink():
                    pairs.append((str(link.resolve()), f"{name}/{link.relative_to(folder)}"))
    return sorted(set(pairs), key=lambda p: -len(p[0]))


def listed(path: str, pairs: list[tuple[str, str]]) -> str | None:
    """`path` as the list writes it, None where it is no simulator data file."""
    path = os.path.normpath(path)
    for real, name in pairs:
        if path == real or path.startswith(real + "/"):
            rel = name + path[len(real):]
            if not rel.endswith(CODE_SUFFIXES) and ".so." not in rel and "/__pycache__/" not in rel \
                    and os.path.isfile(path):
                return rel
    return None


def traced(cells: Path, work: Path) -> tuple[set[str], set[str]]:
    """Every path the RUNS opened (absolute), and the distributions whose modules they loaded."""
    opened: set[str] = set()
    for reset, workers, perturb_cm in RUNS:
        folder = work / f"{reset}-{workers}"
        folder.mkdir()
        log = folder / "strace.txt"
        command = ["strace", "-f", "-qq", "-e", "trace=open,openat", "-o", str(log),
                   *rollout_command(cells, prepared(cells, folder), reset, workers, perturb_cm)]
        done = subprocess.run(command, cwd=ROOT, capture_output=True, text=True)
        if done.returncode:
            sys.exit(f"trace: rollout ({reset} reset, {workers} worker(s)) failed:\n{done.stderr[-3000:]}")
        opened |= opened_paths(log.read_text())
    return opened, imported_distributions(opened)


def opened_paths(log: str) -> set[str]:
    """The paths an `strace -f` log's calls opened: a call another thread interrupted (`<unfinished ...>`) is
    completed by the pid's next `<... openat resumed>` line."""
    paths, pending = set(), {}
    for line in log.splitlines():
        pid = line.split(maxsplit=1)[0]
        if m := CALL.match(line):
            if line.endswith("<unfinished ...>"):
                pending[pid] = m.group(2)
                continue
            path = m.group(2)
        elif "resumed>" in line and pid in pending:
            path = pending.pop(pid)
        else:
            continue
        if OPENED.search(line):
            paths.add(os.path.normpath(os.path.join(ROOT, path)))
    return paths


def imported_distributions(opened: set[str]) -> set[str]:
    """The distributions of the site-packages modules whose files were opened (normalised names)."""
    owners = importlib.metadata.packages_distributions()
    sites = [p for p in sys.path if p.endswith("site-packages")]
    found = set()
    for path in opened:
        for site in sites:
            for prefix in {site, os.path.realpath(site)}:
                if path.startswith(prefix + "/") and path.endswith(CODE_SUFFIXES + (".pth",)):
                    top = path[len(prefix) + 1:].split("/")[0].split(".")[0]
                    found |= {normalised(d) for d in owners.get(top, [])}
    return found


def normalised(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def shell_packages(script: Path) -> set[str]:
    """The `packages=(...)` and `sdists=(...)` arrays of a bundle script."""
    text = script.read_text()
    return {normalised(n) for m in re.finditer(r"^(?:packages|sdists)=\(([^)]*)\)", text, re.M)
            for n in re.sub(r"#.*", "", m.group(1)).split()}


def image_packages() -> set[str]:
    return {normalised(n) for n in IMAGE_PACKAGES.read_text().split() if not n.startswith("#")}


def main(argv: list[str] | None = None) -> None:
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 1:
        sys.exit(__doc__.strip().splitlines()[3].strip())
    cells = Path(args[0]).absolute()
    if not (cells / "results.parquet").is_file() or not (cells / "exports").is_dir():
        sys.exit(f"trace: {cells} holds no results.parquet and exports/ (make it with benchmarks/closed_loop_cells.py)")
    if shutil.which("strace") is None:
        sys.exit("trace: strace is not installed (apt-get install strace)")
    pairs = aliases(package_roots())
    with tempfile.TemporaryDirectory() as work:
        opened, dists = traced(cells, Path(work))
    files = sorted({rel for path in opened if (rel := listed(path, pairs))})
    LIST.write_text("".join(f"{f}\n" for f in files))
    print(f"trace: {len(files)} files into {LIST.relative_to(ROOT)}")
    bundled = shell_packages(HERE / "bundle.sh")
    extra = sorted(dists - image_packages() - bundled - {"graftcache", "lerobot-policy-graftcache"})
    print(f"trace: imported beyond the image and bundle A: {' '.join(extra)}")


if __name__ == "__main__":
    main()
