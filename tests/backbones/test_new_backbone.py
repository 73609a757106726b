"""Adding a backbone is adding its folder and its test file, nothing else (docs/ARCHITECTURE.md, "adding a
backbone"; issue 41): in a copy of the repository, smolvla's folder copied as `smolvla2` (a second adapter of lerobot's
smolvla policy: its adapter.py sets its name and imports its own folder's spec, whose spec.py names the lerobot type it
wraps) and its test file added; the copy's own registry, CLI choices, contract tests, docs checks and report pick
smolvla2 up and pass, run in subprocesses on the copy's code."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow  # ~1-2 min: the contract tests of one more tiny backbone

ROOT = Path(__file__).resolve().parents[2]
NEW, COPIED = "smolvla2", "smolvla"
#: What the copy holds as files (the code it imports and the tests it runs); the rest of the repository is linked.
OWN = ("graftcache", "tests", "devtools")
SKIP = (".git", ".venv", ".ruff_cache")

#: The copy's CLI and report, on the new backbone (run by the copy's Python: its graftcache is the copy's).
CHECKS = textwrap.dedent(f"""
    import argparse, sys
    from pathlib import Path
    import graftcache
    assert Path(graftcache.__file__).resolve().is_relative_to(Path.cwd().resolve()), graftcache.__file__
    from graftcache.backbone_registry import BACKBONES
    from graftcache.cli import build_parser
    assert "{NEW}" in BACKBONES
    commands = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction)).choices
    for command in ("fit", "train-tiny"):
        (flag,) = [a for a in commands[command]._actions if "--backbone" in a.option_strings]
        assert "{NEW}" in flag.choices, (command, flag.choices)
    sys.path.insert(0, "tests")
    from helpers.tables import minimal_table
    from graftcache import report
    table = minimal_table({{("{NEW}", "s", "a"): [1.0, 1.1, 1.2], ("{NEW}", "s", "b"): [2.0, 2.1, 2.2],
                           ("pi05", "s", "a"): [1.0, 1.5, 2.0], ("pi05", "s", "b"): [1.2, 1.4, 1.6]}})
    table.write_parquet("r.parquet")
    assert report.report_command(Path("r.parquet"), Path("report")) == 0
    md = Path("report/report.md").read_text()
    assert "{NEW}: no row records backbone_params (a table from before the column); ordered by the released " \\
           "size, 450M" in md, md
    assert "| SmolVLA | s | a |" in md, md
""")


def _copy(repo: Path) -> None:
    """The repository with backbone NEW added: COPIED's folder under NEW's name, its name and lerobot type set, and
    COPIED's test file for it."""
    repo.mkdir()
    for entry in ROOT.iterdir():
        if entry.name in OWN:
            shutil.copytree(entry, repo / entry.name, ignore=shutil.ignore_patterns("__pycache__"))
        elif entry.name not in SKIP:
            (repo / entry.name).symlink_to(entry)
    folder = repo / "graftcache" / "backbones" / NEW
    shutil.copytree(repo / "graftcache" / "backbones" / COPIED, folder, ignore=shutil.ignore_patterns("__pycache__"))
    adapter, spec = folder / "adapter.py", folder / "spec.py"
    declared = "SPEC = BackboneSpec(\n"
    assert adapter.read_text().count(f'name = "{COPIED}"') == 1 and spec.read_text().count(declared) == 1
    adapter.write_text(adapter.read_text().replace(f'name = "{COPIED}"', f'name = "{NEW}"').replace(
        f"graftcache.backbones.{COPIED}.spec", f"graftcache.backbones.{NEW}.spec"))
    spec.write_text(spec.read_text().replace(declared, f'{declared}    lerobot_type="{COPIED}",\n'))
    tests = repo / "tests" / "backbones"
    (tests / f"test_{NEW}.py").write_text((tests / f"test_{COPIED}.py").read_text().replace(f'"{COPIED}"', f'"{NEW}"'))


def _run(args: list[str], repo: Path) -> str:
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PYTEST_", "PYTHONPATH"))}
    env.update(PYTHONPATH=str(repo), HF_HUB_OFFLINE="1")
    done = subprocess.run([sys.executable, *args], cwd=repo, env=env, capture_output=True, text=True, timeout=900)
    assert done.returncode == 0, done.stdout[-6000:] + done.stderr[-3000:]
    return done.stdout


def test_a_copied_backbone_folder_and_its_test_file_are_a_backbone(tmp_path: Path) -> None:
    repo = tmp_path / "repo"
    _copy(repo)
    _run(["-c", CHECKS], repo)
    out = _run(["-m", "pytest", "-q", "-p", "no:cacheprovider", f"--basetemp={tmp_path / 'inner'}",
          "tests/backbones/test_backbone_registry.py", "tests/backbones/test_contract.py",
          f"tests/backbones/test_{NEW}.py", "tests/test_tests_layout.py", "tests/test_docs.py",
          "-k", f"{NEW} or test_tests_layout or test_docs"], repo)
    passed = re.search(r"(\d+) passed", out)
    assert passed and int(passed.group(1)) >= 30 and " failed" not in out, out[-3000:]  # 14 contract tests, ...
