"""The suite's xdist schedule (tests/helpers/parallel.py): tests/durations.json as devtools/suite_durations.py writes
it from a junit XML, the groups (a tiny-zoo test in its backbone's, across modules) and their order, longest first."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import pytest
from helpers.parallel import TESTS, schedule

from devtools import suite_durations

JUNIT = """<?xml version="1.0" encoding="utf-8"?><testsuites name="pytest tests"><testsuite name="pytest" tests="5">
<testcase classname="tests.test_demo" name="test_demo_runs@test_demo" time="389.295" />
<testcase classname="tests.export.test_export" name="test_export_returns_the_scored_chunk[auto=bf16-eo1]@tiny_zoo-eo1"
 time="25.40" />
<testcase classname="tests.export.test_export" name="test_export_never_writes@tiny_zoo-smolvla" time="6.25" />
<testcase classname="tests.store.test_store.TestLayout" name="test_blocks@store/test_store" time="0.5" />
<testcase classname="tests.store.test_store" name="test_skipped@store/test_store" time="0.0"><skipped /></testcase>
</testsuite></testsuites>
"""


def test_the_tool_sums_each_modules_tests_from_a_junit_xml(tmp_path: Path) -> None:
    junit, out = tmp_path / "run.xml", tmp_path / "durations.json"
    junit.write_text(JUNIT)
    suite_durations.main([str(junit), "--measured", "a run", "--out", str(out)])
    assert json.loads(out.read_text()) == {"format": 1, "measured": "a run", "seconds": {
        "test_demo": 389.3, "export/test_export": 31.6, "store/test_store": 0.5}}
    assert list(suite_durations.read(out)) == ["test_demo", "export/test_export", "store/test_store"]  # longest first
    with pytest.raises(ValueError, match=r"junit classname 'conftest': not a test module under tests/"):
        suite_durations.module_of("conftest")
    out.write_text(json.dumps({"format": 0, "seconds": {}}))
    with pytest.raises(ValueError, match=rf"^{out}: format 0, this schedule reads 1: regenerate it with `python -m "):
        suite_durations.read(out)


@dataclass
class Spec:
    params: dict


@dataclass
class Item:
    """What `schedule` reads of a pytest item, and the markers it adds."""

    module: str
    fixturenames: tuple[str, ...] = ()
    name: str | None = None
    slow: bool = False
    marks: list = field(default_factory=list)

    @property
    def path(self) -> Path:
        return TESTS / f"{self.module}.py"

    def __getattr__(self, attr: str) -> object:  # pytest items without parameters have no callspec
        if attr == "callspec" and self.name is not None:
            return Spec({"name": self.name, "resolution": "bf16"})
        raise AttributeError(attr)

    def get_closest_marker(self, marker: str) -> object:
        return marker == "slow" and self.slow or None

    def add_marker(self, mark: pytest.MarkDecorator) -> None:
        self.marks.append(mark)

    @property
    def group(self) -> str:
        (mark,) = self.marks
        assert mark.name == "xdist_group"
        return mark.args[0]


def test_tiny_zoo_tests_run_in_their_backbones_group_and_the_longest_groups_start_first() -> None:
    zoo = ("tiny_zoo", "capsys")
    items = [Item("backbones/test_zoo_backbones_cli", zoo, "pi0", slow=True),
             Item("backbones/test_zoo_backbones_cli", zoo, "smolvla", slow=True),
             Item("export/test_export", zoo, "smolvla", slow=True), Item("export/test_export", zoo, "pi0", slow=True),
             Item("export/test_export", zoo, slow=True), Item("rollout/test_rollout"), Item("test_cameras"),
             Item("rollout/test_rollout_workers", slow=True), Item("test_new_and_slow", slow=True),
             Item("test_new_and_fast"), Item("test_demo", slow=True)]
    seconds = {"backbones/test_zoo_backbones_cli": 40, "export/test_export": 30, "rollout/test_rollout": 5,
               "rollout/test_rollout_workers": 20, "test_cameras": 1, "test_demo": 300}
    ordered = list(items)
    schedule(ordered, seconds)
    # smolvla: 20 + 10 + 10 (the export test without a name); pi0: 20 + 10; the simulator cells' pair: 5 + 20
    assert [(i.module, i.group) for i in ordered] == [
        ("test_new_and_slow", "test_new_and_slow"), ("test_demo", "test_demo"),
        ("backbones/test_zoo_backbones_cli", "tiny_zoo-smolvla"), ("export/test_export", "tiny_zoo-smolvla"),
        ("export/test_export", "tiny_zoo-smolvla"),
        ("backbones/test_zoo_backbones_cli", "tiny_zoo-pi0"), ("export/test_export", "tiny_zoo-pi0"),
        ("rollout/test_rollout", "simulator_cells"), ("rollout/test_rollout_workers", "simulator_cells"),
        ("test_cameras", "test_cameras"), ("test_new_and_fast", "test_new_and_fast")]
    assert [i.name for i in ordered[2:5]] == ["smolvla", "smolvla", None]
