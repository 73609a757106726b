"""The tests mirror the package: a folder of tests/ per package of graftcache/ (tests of top-level modules at the top),
a file of its own per registered backbone (tests/backbones/test_<name>.py), every test module's name unique (pytest
imports them by basename: no __init__.py in test folders), and the scheduler's modules (tests/helpers/parallel.py's
GROUPS, tests/durations.json) existing."""

from __future__ import annotations

from collections import Counter
from pathlib import Path

from helpers.parallel import GROUPS, TESTS

from devtools.suite_durations import read
from graftcache.backbone_registry import BACKBONES

PACKAGE = TESTS.parent / "graftcache"
#: folders of tests/ that hold no tests: pytest plugins and plain helpers
SUPPORT = {"fixtures", "helpers"}


def _modules() -> list[Path]:
    return sorted(p for p in TESTS.rglob("test_*.py") if "__pycache__" not in p.parts)


def test_every_test_folder_is_a_package_of_graftcache() -> None:
    folders = {p.name for p in TESTS.iterdir() if p.is_dir() and p.name not in SUPPORT | {"__pycache__"}}
    assert folders and sorted(f for f in folders if not (PACKAGE / f).is_dir()) == []
    assert not [p for p in _modules() if len(p.relative_to(TESTS).parts) > 2]  # one level, as the package


def test_test_module_names_are_unique() -> None:
    assert [n for n, k in Counter(p.name for p in _modules()).items() if k > 1] == []
    assert not [p for p in TESTS.rglob("__init__.py") if p.parent.name not in SUPPORT]


def test_every_registered_backbone_has_a_test_file_of_its_own() -> None:
    assert [n for n in BACKBONES if not (TESTS / "backbones" / f"test_{n}.py").is_file()] == []


def test_the_scheduler_names_modules_that_exist() -> None:
    named = set(GROUPS) | set(read())
    assert len(named) > 20  # the file names the run's modules (durations.json is not empty)
    assert sorted(m for m in named if not (TESTS / f"{m}.py").is_file()) == []
