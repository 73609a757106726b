"""`rollout --until-resolved` (graftcache/rollout/sequential.py): looks that add paired episodes only to the candidate
pairs still unresolved, decided from the rows on file, resumable, recorded for the report.

A fake simulator (`ByEncoder`) scripts each episode's closest approach from the cell's encoder: siglip 0.10 m,
resnet18 0.13 m, dinov2-s 0.30 m, plus a jitter of up to 0.04 m drawn from (encoder, fit seed, episode) by a hash,
so dinov2-s is told apart from the others on the first look (2 episodes a cell) while siglip against resnet18 (3 cm
apart under 4 cm of jitter) is not, and is on the second (4). Each look's decision is checked against
graftcache.analysis.pairwise run independently on exactly that look's episodes, at the level the record states.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping
from functools import partial
from pathlib import Path
from typing import Any

import polars as pl
import pytest
from helpers.rollouts import Scripted
from helpers.tables import write_results

from graftcache.analysis.looks import LOOKS_FILE
from graftcache.analysis.pairwise import pairwise
from graftcache.analysis.rollouts import read_rollouts
from graftcache.errors import RolloutError
from graftcache.results import read_for_report
from graftcache.rollout import rollouts_file
from graftcache.rollout.episodes import Episode, Outcome
from graftcache.rollout.graded import Graded
from graftcache.rollout.request import RolloutRequest
from graftcache.rollout.roll_out import roll_out_started
from graftcache.rollout.select import select
from graftcache.rollout.sequential import Sequential, looks

BASE = {"siglip": 0.10, "resnet18": 0.13, "dinov2-s": 0.30}


def _jitter(*key: object) -> float:
    digest = hashlib.sha256(repr(key).encode()).digest()
    return 0.04 * (digest[0] / 255 * 2 - 1)


class ByEncoder(Scripted):
    """A Simulator whose closest approach depends on the cell's encoder (the module docstring); `stop_after`: raise
    after that many episodes, as a killed run would."""

    def outcome(self, row: Mapping[str, Any], e: Episode) -> Outcome:
        distance = BASE.get(row["encoder"], 0.5) + _jitter(row["encoder"], row["seed"], e.episode)
        graded = Graded(target="bowl_1", min_target_distance_m=distance, final_target_distance_m=distance,
                        target_lift_m=0.0, grasped=False, goal_fraction=0.0)
        return Outcome(success=False, steps=5, seconds=0.1, init_state=e.episode, graded=graded,
                       target_offset_m=(0.0, 0.0))


def _request(tmp_path: Path, **over: Any) -> RolloutRequest:
    results = write_results(tmp_path / "results.parquet")
    fields = {"results": results, "rollouts": tmp_path / "rollouts.parquet", "top": 3, "suites": ("libero_spatial",),
              "tasks": (0,), "episodes_per_task": 2, "seed": 11, "command": "graftcache rollout --until-resolved 6"}
    return RolloutRequest(**{**fields, **over})


def _run(req: RolloutRequest, sim: ByEncoder, seq: Sequential) -> list[str]:
    lines: list[str] = []
    roll_out_started([select(req)], lambda: sim, None, lines.append, expand=partial(looks, seq=seq, log=lines.append))
    return lines


def _per_cell(req: RolloutRequest) -> pl.DataFrame:
    rows = rollouts_file.read(req.rollouts).join(read_for_report(req.results), on="run_id", suffix="_cell")
    return rows.group_by("backbone", "control", "encoder", "seed_cell").agg(n=pl.len())


def test_looks_add_episodes_only_to_unresolved_candidate_pairs(tmp_path: Path) -> None:
    req, seq = _request(tmp_path), Sequential(cap=6)
    lines = _run(req, ByEncoder(), seq)
    record = json.loads((tmp_path / LOOKS_FILE).read_text())
    assert (record["looks_planned"], record["level"], record["step"]) == (3, pytest.approx(1 - 0.05 / 3), 2)
    assert lines[0].startswith("sequential rollout: up to 3 look(s) of 2 episode(s) per task (cap 6)")
    counts = _per_cell(req)
    # controls and dinov2-s (resolved against both on the first look) keep the first look's 2 episodes
    first_only = counts.filter((pl.col("control") != "none") | (pl.col("encoder") == "dinov2-s"))
    assert first_only.height and set(first_only["n"].to_list()) == {2}
    results = read_for_report(req.results)
    candidates = results.filter(pl.col("control") == "none", pl.col("suite") == "libero_spatial")
    # every look's decision is pairwise's own on exactly that look's episodes
    for look in record["looks"]:
        n = look["episodes_per_task"]
        episodes = read_rollouts(req.rollouts, results, where=pl.col("episode") < n)
        expected = pairwise(candidates, episodes, measure=seq.measure, closed_level=record["level"]).filter(
            pl.col("closed") == "not resolved").select("backbone", "suite", "encoder_a", "encoder_b").rows()
        assert sorted(map(tuple, look["unresolved"])) == sorted(expected)
    assert record["looks"][0]["unresolved"], "the scripted siglip/resnet18 pair must be unresolved on the first look"
    assert all(p[2:] == ["resnet18", "siglip"] for p in record["looks"][0]["unresolved"])
    # the unresolved pair's cells, and only they, went on to the second look, which resolved it: no third
    went_on = counts.filter(pl.col("control") == "none", pl.col("encoder").is_in(["resnet18", "siglip"]))
    assert went_on.height == 2 * 3 * 2 and set(went_on["n"].to_list()) == {4}
    assert [(look["episodes_per_task"], len(look["unresolved"])) for look in record["looks"]] == [(2, 2), (4, 0)]


def test_a_killed_sequential_rollout_resumes_to_the_same_rows_and_record(tmp_path: Path) -> None:
    seq = Sequential(cap=6)
    whole, cut = tmp_path / "whole", tmp_path / "cut"
    whole.mkdir()
    cut.mkdir()
    _run(_request(whole), ByEncoder(), seq)
    with pytest.raises(KeyboardInterrupt):
        _run(_request(cut), ByEncoder(stop_after=60), seq)  # inside the second look (the first has 52 episodes)
    assert not (cut / LOOKS_FILE).exists()
    again = ByEncoder()
    _run(_request(cut), again, seq)
    assert again.ran and len(again.ran) < len(rollouts_file.read(whole / "rollouts.parquet"))
    key = ["run_id", "episode_id", "min_target_distance_m"]
    assert rollouts_file.read(cut / "rollouts.parquet").select(key).sort(key).equals(
        rollouts_file.read(whole / "rollouts.parquet").select(key).sort(key))
    assert rollouts_file.read(cut / "rollouts.parquet")["episode_id"].is_unique().all()
    assert json.loads((cut / LOOKS_FILE).read_text())["looks"] == json.loads(
        (whole / LOOKS_FILE).read_text())["looks"]


@pytest.mark.parametrize(("over", "message"), [
    ({"cap": 0}, "--until-resolved 0: must be 1 to 1000"),
    ({"cap": 4, "error": 1.0}, "sequential error rate 1.0: must lie strictly between 0 and 1"),
    ({"cap": 4, "measure": "speed"}, "sequential measure speed: not a closed-loop measure"),
])
def test_bad_sequential_settings_are_refused_in_one_line(over: dict, message: str) -> None:
    with pytest.raises(RolloutError, match=f"^{message}"):
        Sequential(**over)


def test_a_first_look_past_the_cap_is_refused(tmp_path: Path) -> None:
    with pytest.raises(RolloutError, match="^--episodes-per-task 2 is past --until-resolved 1"):
        _run(_request(tmp_path), ByEncoder(), Sequential(cap=1))


def test_the_report_takes_the_looks_level_and_states_the_error_rate(tmp_path: Path) -> None:
    """The closed-loop side of the report's pairwise table is at the looks' level (scipy's t interval of the pair's
    differences at 1 - 0.05 / 3), not 95%, and the report says how the episodes were spent."""
    from scipy import stats

    from graftcache import analysis as A
    from graftcache.report import write_report

    req = _request(tmp_path)
    _run(req, ByEncoder(), Sequential(cap=6))
    looks = A.read_looks(req.rollouts)
    assert looks is not None and (looks.level, len(looks.looks)) == (pytest.approx(1 - 0.05 / 3), 2)
    write_report(req.results, tmp_path / "report", rollouts=req.rollouts)
    table = pl.read_csv(tmp_path / "report" / "pairwise.csv").filter(
        pl.col("measure") == "min_target_distance_m", pl.col("backbone") == "smolvla",
        pl.col("suite") == "libero_spatial", pl.col("encoder_a") == "resnet18", pl.col("encoder_b") == "siglip",
    ).row(0, named=True)
    rollouts = table_of(req)
    by_cell = {(r["seed_cell"], r["episode"]): r["min_target_distance_m"]
               for r in rollouts.filter(pl.col("backbone") == "smolvla").iter_rows(named=True)
               if r["control"] == "none" and r["encoder"] == "resnet18"}
    diffs = [v - next(r["min_target_distance_m"] for r in rollouts.iter_rows(named=True)
                      if (r["backbone"], r["control"], r["encoder"], r["seed_cell"], r["episode"])
                      == ("smolvla", "none", "siglip", s, k)) for (s, k), v in by_cell.items()]
    low, high = stats.t.interval(looks.level, len(diffs) - 1, loc=sum(diffs) / len(diffs), scale=stats.sem(diffs))
    assert (table["pairs"], table["closed_low"], table["closed_high"]) == (len(diffs), pytest.approx(low),
                                                                            pytest.approx(high))
    text = (tmp_path / "report" / "report.md").read_text()
    assert "`rollout --until-resolved 6`" in text and "taken at 98.33% (Bonferroni over the looks)" in text
    assert "chance at most 5% whatever look it stopped at. 2 look(s) ran" in text


def table_of(req: RolloutRequest) -> pl.DataFrame:
    return rollouts_file.read(req.rollouts).join(read_for_report(req.results), on="run_id", suffix="_cell")


def test_a_request_without_two_candidate_encoders_runs_once(tmp_path: Path) -> None:
    """Only controls (no pair of candidate encoders to judge): one look, said so, recorded with nothing unresolved."""
    results = read_for_report(write_results(tmp_path / "results.parquet"))
    zero = results.filter(pl.col("control") == "zero-image", pl.col("suite") == "libero_spatial")["run_id"][:2]
    sim = ByEncoder()
    lines = _run(_request(tmp_path, run_ids=tuple(zero)), sim, Sequential(cap=6))
    assert len(sim.ran) == 2 * 2 and any("no pair to judge: one look" in line for line in lines)
    assert json.loads((tmp_path / LOOKS_FILE).read_text())["looks"] == [
        {"look": 1, "episodes_per_task": 2, "cells": 2, "unresolved": []}]
