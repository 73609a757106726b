"""`python -m devtools.suite_durations JUNIT_XML --measured TEXT`: tests/durations.json from the junit XML of a full
run of the suite (`pytest ... --junitxml=FILE`): the seconds each test module's tests took there, which the suite's
schedule (tests/helpers/parallel.py) orders the xdist groups by, longest first. Regenerate it from a clean-clone CI
run when modules are added or change cost; a module the file does not name is scheduled by its slow marker alone.

File format 1: {"format": 1, "measured": "<the run: date, machine>", "seconds": {"<module>": seconds}}, a module
named by its path under tests/ without ".py" ("export/test_export"), as tests/helpers/parallel.py names them.
"""

from __future__ import annotations

import argparse
import json
import xml.etree.ElementTree as ET
from collections import defaultdict
from pathlib import Path

FORMAT = 1
DURATIONS = Path(__file__).resolve().parents[1] / "tests" / "durations.json"


def module_of(classname: str) -> str:
    """A junit testcase's classname -> its module under tests/: "tests.export.test_export" (or a class in it,
    "tests.export.test_export.TestX") -> "export/test_export"."""
    parts = classname.split(".")
    files = [i for i, part in enumerate(parts) if part.startswith("test_")]
    if parts[0] != "tests" or not files:
        raise ValueError(f"junit classname {classname!r}: not a test module under tests/ (run pytest from the "
                         "repository root)")
    return "/".join(parts[1:files[-1] + 1])


def parse(junit: Path) -> dict[str, float]:
    """Seconds per test module (its testcases' times summed), longest first."""
    seconds: dict[str, float] = defaultdict(float)
    for case in ET.parse(junit).getroot().iter("testcase"):
        seconds[module_of(case.get("classname", ""))] += float(case.get("time", 0))
    return {m: round(s, 1) for m, s in sorted(seconds.items(), key=lambda kv: (-kv[1], kv[0]))}


def write(path: Path, seconds: dict[str, float], measured: str) -> None:
    path.write_text(json.dumps({"format": FORMAT, "measured": measured, "seconds": seconds}, indent=1) + "\n")


def read(path: Path = DURATIONS) -> dict[str, float]:
    """The seconds per module a durations file holds; another format is one line naming the file and the fix."""
    data = json.loads(path.read_text())
    if data.get("format") != FORMAT:
        raise ValueError(f"{path}: format {data.get('format')}, this schedule reads {FORMAT}: regenerate it with "
                         "`python -m devtools.suite_durations JUNIT_XML --measured TEXT`")
    return data["seconds"]


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], prog="python -m devtools.suite_durations")
    p.add_argument("junit", type=Path, help="junit XML of a full run of the suite (pytest --junitxml)")
    p.add_argument("--measured", required=True, help="the run, as the file records it: date, CPU, workers")
    p.add_argument("--out", type=Path, default=DURATIONS, help=f"the durations file (default: {DURATIONS})")
    args = p.parse_args(argv)
    write(args.out, parse(args.junit), args.measured)


if __name__ == "__main__":
    main()
