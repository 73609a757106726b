"""The tiny zoo's builds (tests/fixtures/tiny_zoo.py) are made once per run, by whichever xdist worker asks first, and
read back by the other: here two TinyZoo objects on one folder stand for the two workers, with a stand-in command."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import pytest
from fixtures.tiny_zoo import TinyZoo
from helpers.probes import Outcome


class Command:
    """A build that counts its runs, writes into `folder`, and ends as `code`."""

    def __init__(self, folder: Path, code: int = 0) -> None:
        self.folder, self.code, self.runs = folder, code, 0

    def __call__(self) -> Outcome:
        self.runs += 1
        assert not (self.folder / "half").exists()  # never built over a half-made build
        self.folder.mkdir(parents=True, exist_ok=True)
        time.sleep(0.2)  # long enough for the other worker to ask meanwhile
        (self.folder / "built").write_text(str(self.runs))
        return Outcome(self.code, f"built {self.runs}\n", "" if self.code == 0 else "failed: disk full\n")


def test_two_workers_asking_at_once_build_once_and_read_the_same_outcome(tmp_path: Path) -> None:
    build = Command(tmp_path / "pi0" / "policy")
    got: dict[str, Outcome] = {}

    def worker(gw: str) -> None:
        got[gw] = TinyZoo(tmp_path, "bf16")._once("pi0", tmp_path / "pi0" / "policy.json", build, build.folder)

    threads = [threading.Thread(target=worker, args=(gw,)) for gw in ("gw0", "gw1")]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert build.runs == 1 and got["gw0"] == got["gw1"] == Outcome(0, "built 1\n", "")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["pi0"]  # the lease file went with its holder
    assert sorted(p.name for p in (tmp_path / "pi0").iterdir()) == ["policy", "policy.json"]


def test_a_half_made_build_is_removed_and_made_again_and_a_failed_one_leaves_no_outcome(tmp_path: Path) -> None:
    done, folder = tmp_path / "pi0" / "policy.json", tmp_path / "pi0" / "policy"
    folder.mkdir(parents=True)
    (folder / "half").write_text("a worker killed mid-way")
    failing = Command(folder, code=1)
    with pytest.raises(AssertionError, match="failed: disk full"):
        TinyZoo(tmp_path, "bf16")._once("pi0", done, failing, folder)
    assert failing.runs == 1 and not done.exists() and (folder / "built").read_text() == "1"
    (folder / "half").write_text("a worker killed mid-way")
    build = Command(folder)
    assert TinyZoo(tmp_path, "bf16")._once("pi0", done, build, folder) == Outcome(0, "built 1\n", "")
    assert build.runs == 1 and sorted(p.name for p in folder.iterdir()) == ["built"]
    again = Command(folder)
    assert TinyZoo(tmp_path, "bf16")._once("pi0", done, again, folder).out == "built 1\n" and again.runs == 0
