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


REPORT = """
import contextlib, io, json, sys
from graftcache.cli import main
with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
    code = main(["report", sys.argv[1], "--out", sys.argv[2]])
print(json.dumps({"code": code, "heavy": [m for m in sys.argv[3:] if m in sys.modules]}))
"""


def test_a_report_reads_backbone_labels_and_released_sizes_without_a_model_library(tmp_path: Path) -> None:
    """Each backbone's label and released size come from its folder's spec.py (graftcache.backbones.registered_spec),
    not its adapter: `graftcache report` on a table of every backbone with a released size, which the ladder orders
    them by (the table records no backbone_params), imports no model library."""
    from helpers.tables import minimal_table

    from graftcache.backbone_registry import BACKBONES
    from graftcache.backbones import registered_spec

    sized = [name for name in BACKBONES if registered_spec(name).released_params]
    assert len(sized) >= 3
    table = minimal_table({(name, "s", encoder): [1.0 + i, 1.1 + i, 1.2 + i] for i, name in enumerate(sized)
                           for encoder in ("a", "b")})
    table.write_parquet(tmp_path / "r.parquet")
    path = os.pathsep.join([str(Path(__file__).resolve().parents[2]), os.environ.get("PYTHONPATH", "")])
    child = subprocess.run([sys.executable, "-c", REPORT, str(tmp_path / "r.parquet"), str(tmp_path / "report"),
                            *HEAVY], capture_output=True, text=True, env={**os.environ, "PYTHONPATH": path},
                           timeout=300, check=True)
    assert json.loads(child.stdout) == {"code": 0, "heavy": []}
    md = (tmp_path / "report" / "report.md").read_text()
    assert [name for name in sized if f"| {registered_spec(name).label} | s | a |" not in md] == []
    assert "ordered by the released size" in md
