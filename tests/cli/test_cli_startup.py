"""`graftcache --help` and `graftcache ls` start without torch: building the parser imports no model library
(choices are plain data, help that lists a heavy registry is made only when printed), and listing caches reads
manifests and folders only. A subprocess, because what a fresh process imports is the thing tested."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

from helpers.caches import synthetic_cache

#: Libraries that take seconds to import; none may load to print help or list caches.
HEAVY = ("torch", "torchvision", "transformers", "timm", "lerobot")
CHILD = """
import contextlib, io, json, sys
from graftcache.cli import main
out = io.StringIO()
with contextlib.redirect_stdout(out):
    codes = [main(["ls", "--cache", sys.argv[1]])]
    for argv in (["--help"], ["fit", "--help"], ["report", "--help"]):
        try:
            main(argv)
        except SystemExit as e:
            codes.append(e.code)
print(json.dumps({"codes": codes, "out": out.getvalue(), "heavy": [m for m in sys.argv[2:] if m in sys.modules]}))
"""


def test_help_and_ls_import_no_model_library(tmp_path: Path) -> None:
    cache = synthetic_cache(tmp_path / "root", [3, 2])
    path = os.pathsep.join([str(Path(__file__).resolve().parents[2]), os.environ.get("PYTHONPATH", "")])
    child = subprocess.run([sys.executable, "-c", CHILD, str(tmp_path / "root"), *HEAVY], capture_output=True,
                           text=True, env={**os.environ, "PYTHONPATH": path}, timeout=120, check=True)
    got = json.loads(child.stdout)
    assert got["heavy"] == [], got["heavy"]
    assert got["codes"] == [0, 0, 0, 0]
    out = " ".join(got["out"].split())  # help as words, however argparse wrapped it
    assert cache.key in out  # ls read the cache
    for command in ("extract", "fit", "sweep", "ls", "report"):  # the top-level help lists the commands
        assert command in out
    # help made only when printed: the suites datasets.suites knows, the columns a report needs
    assert "LIBERO suite: libero_spatial, libero_object, libero_goal, libero_10, libero_90" in out
    assert "backbone, suite, encoder, control, seed, eval_mse" in out
