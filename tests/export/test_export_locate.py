"""`graftcache export` with a wrong `--cache` (an empty folder, another root, the cache folder itself) is refused in
one line naming the root searched and the cache the row needs, before torch or the base policy load (it said
"<key>: no feature cache here (zarr.json missing)" after the loading before)."""

from __future__ import annotations

from pathlib import Path

import pytest
from helpers.probes import finish, run_cli, start_process
from helpers.tables import row, table

from graftcache import results

KEY = "resnet18-0123456789abcdef"


@pytest.fixture
def results_file(tmp_path: Path) -> tuple[Path, str]:
    made = row("smolvla", "libero_spatial", "resnet18", 0, 1.0, cache_key=KEY)
    path = tmp_path / "results.parquet"
    results.append(path, table([made]))
    return path, made["run_id"]


def test_a_wrong_cache_root_is_named_and_the_fit_s_root_asked_for(tmp_path: Path, results_file: tuple[Path, str],
                                                                   capsys: pytest.CaptureFixture) -> None:
    path, run_id = results_file
    empty, root = tmp_path / "empty", tmp_path / "root"
    empty.mkdir()
    (root / KEY).mkdir(parents=True)
    (root / KEY / "zarr.json").write_text("{}")
    export = ["export", run_id, "--results", str(path), "--out", str(tmp_path / "out")]
    for given, what in ((empty, f"holds no cache {KEY}"),
                        (root / KEY, "is a feature cache itself, not a cache root (pass the folder holding it)")):
        refused = run_cli([*export, "--cache", str(given)], capsys)
        assert (refused.code, refused.out) == (2, "")
        assert refused.err == (f"graftcache export: error: run {run_id}: cache root {given} {what}; pass the --cache "
                               f"its fit used (the root holding {KEY}/)\n")
    assert not (tmp_path / "out").exists()


def test_the_refusal_comes_before_torch_is_imported(tmp_path: Path, results_file: tuple[Path, str]) -> None:
    path, run_id = results_file
    prelude = "import atexit, sys\natexit.register(lambda: print('torch' in sys.modules, file=sys.stdout))"
    child = start_process(["export", run_id, "--results", path, "--out", tmp_path / "out", "--cache", tmp_path],
                          prelude=prelude)
    done = finish(child)
    assert done.code == 2 and f"cache root {tmp_path} holds no cache {KEY}" in done.err
    assert done.out.strip() == "False"  # torch never imported
