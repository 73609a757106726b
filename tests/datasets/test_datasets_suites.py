"""Task instruction -> LIBERO suite, from the shipped resources/libero_suite_tasks.json."""

from __future__ import annotations

import pytest
from helpers.datasets import Written

from graftcache.datasets import open_dataset, suite_of
from graftcache.datasets.suites import suite_tasks

MAIN_SUITES = ("libero_spatial", "libero_object", "libero_goal", "libero_10")


def test_all_40_main_suite_instructions_map_to_their_suite() -> None:
    table = suite_tasks()
    pairs = [(task, suite) for suite in MAIN_SUITES for task in table[suite]]
    assert len(pairs) == 40 and len({t for t, _ in pairs}) == 40
    assert [suite_of(t) for t, _ in pairs] == [s for _, s in pairs]


def test_shared_libero_90_instructions_prefer_the_evaluation_suite() -> None:
    table = suite_tasks()
    shared = set(table["libero_90"]) & {t for s in MAIN_SUITES for t in table[s]}
    assert shared == {"turn on the stove", "pick up the book and place it in the back compartment of the caddy"}
    assert suite_of("turn on the stove") == "libero_goal"
    assert suite_of("pick up the book and place it in the back compartment of the caddy") == "libero_10"
    only_90 = [t for t in table["libero_90"] if t not in shared]
    assert only_90 and {suite_of(t) for t in only_90} == {"libero_90"}


@pytest.mark.parametrize("text", ["Open the middle drawer of the cabinet.",
                                  "  open the middle  drawer of the cabinet "])
def test_case_spacing_and_final_period_do_not_matter(text: str) -> None:
    assert suite_of(text) == "libero_goal"


@pytest.mark.parametrize("text", ["fold the towel", "", "open the middle drawer"])
def test_unknown(text: str) -> None:
    assert suite_of(text) == "unknown"


def test_suites_of_a_dataset(v2_pi: Written) -> None:
    assert [suite_of(t) for t in open_dataset(v2_pi.root).meta.tasks] == ["libero_spatial", "libero_object"]
