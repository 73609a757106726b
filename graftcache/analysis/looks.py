"""The record of a sequential rollout's looks (`graftcache rollout --until-resolved`, graftcache.rollout.sequential),
as the report reads it: how many looks of how many episodes, the cap, the error rate spent over the looks and the
level each look's closed-loop interval was taken at, and which candidate pairs were still unresolved after each.

Why the report needs it: a pair's closed-loop interval taken at 95% after episodes were added until it excluded 0
would not hold its 95% (each look is another chance to stop on noise). The looks were decided at a stricter level
(the error spread over the looks), so the report takes the closed-loop side of its pairwise verdicts at that level
and says so; without a record, the rollouts had a fixed count and 95% stands.

The file sits beside the rollouts file (LOOKS_FILE), written whole by the rollout, typed and versioned here: the
analysis reads files, it does not depend on the code that writes them.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from graftcache.errors import GraftcacheError

#: Beside the rollouts file: what the looks of the last sequential rollout into it decided
LOOKS_FILE = "sequential.json"
#: The format of LOOKS_FILE this code reads and writes
FORMAT_VERSION = 1
#: The closed-loop interval level without a sequential record
FIXED_LEVEL = 0.95


@dataclass(frozen=True)
class Look:
    """One look: every cell it judged had `episodes_per_task` episodes a task; `cells` ran them; `unresolved`
    lists the candidate pairs (backbone, suite, encoder_a, encoder_b) still unresolved after it."""

    look: int
    episodes_per_task: int
    cells: int
    unresolved: tuple[tuple[str, str, str, str], ...]


@dataclass(frozen=True)
class Looks:
    """A sequential rollout's record: looks of `step` episodes per task up to `cap`, at most `max_looks` of
    them, each judged on `measure` at `level` = 1 - `error` / `max_looks` (its stored key keeps the
    name sequential.json has always had, so older records read unchanged)."""

    measure: str
    error: float
    cap: int
    step: int
    max_looks: int
    level: float
    looks: tuple[Look, ...]
    command: str = ""

    def as_json(self) -> dict:
        return {"format_version": FORMAT_VERSION, "measure": self.measure, "error": self.error, "cap": self.cap,
                "step": self.step, "looks_planned": self.max_looks, "level": self.level, "command": self.command,
                "looks": [{"look": k.look, "episodes_per_task": k.episodes_per_task, "cells": k.cells,
                           "unresolved": [list(p) for p in k.unresolved]} for k in self.looks]}


def looks_file(rollouts: str | Path) -> Path:
    return Path(rollouts).parent / LOOKS_FILE


def read_looks(rollouts: str | Path) -> Looks | None:
    """The record beside the rollouts file `rollouts`, or None where there is none (fixed episode counts). A file
    that is not such a record is refused in one line naming it."""
    path = looks_file(rollouts)
    if not path.is_file():
        return None
    try:
        raw = json.loads(path.read_text())
        if raw.get("format_version") != FORMAT_VERSION:
            raise GraftcacheError(f"{path}: sequential record of format {raw.get('format_version')!r}; this "
                                  f"graftcache reads format {FORMAT_VERSION}")
        looks = tuple(Look(int(k["look"]), int(k["episodes_per_task"]), int(k["cells"]),
                           tuple(tuple(str(x) for x in p) for p in k["unresolved"])) for k in raw["looks"])
        return Looks(str(raw["measure"]), float(raw["error"]), int(raw["cap"]), int(raw["step"]),
                     int(raw["looks_planned"]), float(raw["level"]), looks, str(raw.get("command", "")))
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as e:
        raise GraftcacheError(f"{path}: not a sequential rollout record ({type(e).__name__}: {e})") from None
