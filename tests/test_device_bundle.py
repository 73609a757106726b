"""The closed-loop bundle's inputs stay true to the installed simulator (benchmarks/device/): every data file
closed_loop_files.txt lists is still where robosuite and hf-libero install it (a version bump that moves one fails
here, not on a lent GPU machine), the strace log is read as the kernel answered, the bundle carries nothing the
device already has, and the device scripts parse."""

from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest

DEVICE = Path(__file__).resolve().parents[1] / "benchmarks" / "device"
SCRIPTS = ("bundle.sh", "run.sh", "bundle_closed_loop.sh", "run_closed_loop.sh", "cp312_wheels.sh")


@pytest.fixture
def tracing(monkeypatch: pytest.MonkeyPatch):
    monkeypatch.syspath_prepend(str(DEVICE))
    monkeypatch.delitem(sys.modules, "trace_closed_loop_files", raising=False)
    import trace_closed_loop_files

    return trace_closed_loop_files


def test_every_listed_simulator_file_is_installed() -> None:
    listed = (DEVICE / "closed_loop_files.txt").read_text().split()
    site = Path(importlib.util.find_spec("robosuite").origin).parents[1]
    assert Path(importlib.util.find_spec("libero").submodule_search_locations[0]).parent == site
    assert {"robosuite/models/assets/base.xml", "robosuite/models/assets/robots/panda/robot.xml"} <= set(listed)
    assert any(f.startswith("libero/libero/assets/") for f in listed)
    assert listed == sorted(set(listed))
    assert [f for f in listed if not (site / f).is_file()] == []


def test_a_traced_open_counts_only_where_it_returned_a_descriptor(tracing) -> None:
    log = "\n".join([
        '7 openat(AT_FDCWD, "/a/found.xml", O_RDONLY|O_CLOEXEC) = 3',
        '7 openat(AT_FDCWD, "/a/missing.xml", O_RDONLY|O_CLOEXEC) = -1 ENOENT (No such file or directory)',
        '8 open("rel/../b.png", O_RDONLY) = 12',
        '9 openat(AT_FDCWD, "/a/slow.msh", O_RDONLY <unfinished ...>',
        '7 openat(AT_FDCWD, "/a/other.stl", O_RDONLY <unfinished ...>',
        '9 <... openat resumed>)             = 5',
        '7 <... openat resumed>)             = -1 EACCES (Permission denied)',
        '8 +++ exited with 0 +++',
    ])
    assert tracing.opened_paths(log) == {"/a/found.xml", "/a/slow.msh", str(tracing.ROOT / "b.png")}


def test_a_file_under_a_linked_folder_is_listed_where_it_is_linked_from(tracing, tmp_path: Path) -> None:
    assets = tmp_path / "cache" / "assets"
    (assets / "scenes").mkdir(parents=True)
    (assets / "scenes" / "floor.xml").write_text("<mujoco/>")
    package = tmp_path / "site" / "libero"
    (package / "libero").mkdir(parents=True)
    (package / "libero" / "assets").symlink_to(assets)
    (package / "libero" / "benchmark.py").write_text("")
    pairs = tracing.aliases({"libero": package})
    assert tracing.listed(str(assets / "scenes" / "floor.xml"), pairs) == "libero/libero/assets/scenes/floor.xml"
    assert tracing.listed(str(package / "libero" / "x" / ".." / "assets" / "scenes" / "floor.xml"), pairs) == \
        "libero/libero/assets/scenes/floor.xml"
    assert tracing.listed(str(package / "libero" / "benchmark.py"), pairs) is None  # Python is not data
    assert tracing.listed(str(tmp_path / "elsewhere.xml"), pairs) is None


def test_the_closed_loop_bundle_carries_nothing_the_image_or_bundle_a_has(tracing) -> None:
    closed_loop = tracing.shell_packages(DEVICE / "bundle_closed_loop.sh")
    assert {"mujoco", "robosuite", "hf-libero", "bddl", "polars", "polars-runtime-32"} <= closed_loop
    assert {"lerobot", "transformers", "docopt"} <= tracing.shell_packages(DEVICE / "bundle.sh")
    assert {"torch", "numpy", "opencv-python-headless", "numba"} <= tracing.image_packages()
    assert closed_loop & (tracing.image_packages() | tracing.shell_packages(DEVICE / "bundle.sh")) == set()


@pytest.mark.parametrize("script", SCRIPTS)
def test_the_device_scripts_parse(script: str) -> None:
    done = subprocess.run(["bash", "-n", str(DEVICE / script)], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
