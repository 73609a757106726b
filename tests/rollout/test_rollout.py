"""`graftcache rollout` (issue 31, item 3): which rows it runs, how it resumes, and (slow) the CI smoke in the real
LIBERO simulator.

The selection and resume tests run without the simulator: a fake (`Scripted`) stands behind the Simulator interface
(graftcache.rollout.episodes.Simulator) and scripts each episode's outcome from its seed. The hand-built results
table is tests/helpers/tables.py's: on smolvla/libero_spatial siglip (mean 1.1) < dinov2-s (2.1) < resnet18 (3.1),
with zero-image rows of siglip and resnet18, shuffled-image of siglip, native 1.0 and native-graft; on
pi05/libero_spatial dinov2-s (1.4) < siglip (1.5) < resnet18, and a native row.
"""

from __future__ import annotations

import hashlib
import importlib.metadata
import importlib.util
import json
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import polars as pl
import pytest
from fixtures.simulator_cells import Fitted
from helpers.rollouts import Scripted, rolled
from helpers.tables import full_table, row, write_results
from helpers.tables import table as results_table

from graftcache import results
from graftcache.errors import RolloutError
from graftcache.results.claims import claims_folder
from graftcache.rollout import record, rollouts_file
from graftcache.rollout.episodes import Episode, Outcome
from graftcache.rollout.graded import Graded
from graftcache.rollout.request import RolloutRequest
from graftcache.rollout.select import select_rows


def _keys(rows: pl.DataFrame) -> list[tuple]:
    return rows.select("backbone", "suite", "control", "encoder", "seed").rows()


def test_top_k_takes_the_reports_best_encoders_every_seed_with_their_controls() -> None:
    chosen = select_rows(full_table(), top=2, suites=["libero_spatial"])
    smolvla = [k for k in _keys(chosen) if k[0] == "smolvla"]
    assert smolvla == [("smolvla", "libero_spatial", "native", "smolvla-native", 0),
                       *[("smolvla", "libero_spatial", "none", e, s) for e in ("dinov2-s", "siglip") for s in range(3)],
                       *[("smolvla", "libero_spatial", "zero-image", "siglip", s) for s in range(3)]]
    # pi05: dinov2-s and siglip are its best two (resnet18 is not), and it has no zero-image rows
    pi05 = [k for k in _keys(chosen) if k[0] == "pi05"]
    assert pi05 == [("pi05", "libero_spatial", "native", "pi05-native", 0),
                    *[("pi05", "libero_spatial", "none", e, s) for e in ("dinov2-s", "siglip") for s in range(3)]]
    assert "shuffled-image" not in chosen["control"].to_list()  # siglip's shuffled-image rows are never picked
    assert "native-graft" not in chosen["control"].to_list()


def test_top_1_per_suite_and_backbone() -> None:
    chosen = select_rows(full_table(), top=1)
    plain = chosen.filter(pl.col("control") == "none").select("backbone", "suite", "encoder").unique().sort(
        "backbone", "suite").rows()
    # libero_10 smolvla: siglip and dinov2-s tie at mean 2.0, the report's order (rank, then name) puts dinov2-s first
    assert plain == [("pi05", "libero_10", "dinov2-s"), ("pi05", "libero_goal", "dinov2-s"),
                     ("pi05", "libero_object", "dinov2-s"), ("pi05", "libero_spatial", "dinov2-s"),
                     ("smolvla", "libero_10", "dinov2-s"), ("smolvla", "libero_goal", "siglip"),
                     ("smolvla", "libero_object", "siglip"), ("smolvla", "libero_spatial", "siglip")]


def test_run_ids_are_taken_exactly_and_refusals_name_the_run() -> None:
    results = full_table()
    ids = {(r["backbone"], r["suite"], r["encoder"], r["control"], r["seed"]): r["run_id"]
           for r in results.iter_rows(named=True)}
    a, b = ids["smolvla", "libero_spatial", "resnet18", "none", 2], ids["pi05", "libero_object", "siglip", "none", 0]
    assert set(select_rows(results, run_ids=[a, b])["run_id"].to_list()) == {a, b}
    assert select_rows(results, run_ids=[a]).height == 1  # no controls added to exact run_ids
    shuffled = ids["smolvla", "libero_spatial", "siglip", "shuffled-image", 0]
    with pytest.raises(RolloutError) as refused:
        select_rows(results, run_ids=[a, shuffled])
    assert str(refused.value) == (f"run {shuffled} (smolvla/siglip/libero_spatial, control shuffled-image): control "
                                  "shuffled-image has no closed-loop meaning (it feeds features of other frames); "
                                  "roll out another control")
    with pytest.raises(RolloutError, match="^run 0123456789abcdef: no such row in the results file$"):
        select_rows(results, run_ids=["0123456789abcdef"])
    with pytest.raises(RolloutError, match=f"^run {b}: fit on libero_object, not among --suites libero_spatial$"):
        select_rows(results, run_ids=[b], suites=["libero_spatial"])


def test_run_ids_of_one_policy_are_rolled_out_once_and_the_log_says_which() -> None:
    """Two zero-image runs of one policy (format 6: zero-image ignores the encoder's cache) asked by run_id: the
    first encoder's by name is rolled out, for both, in one line; a run of another policy is kept as asked."""
    rows = [row("smolvla", "libero_spatial", e, 0, 3.0, control="zero-image", policy_id="0123456789abcdef")
            for e in ("siglip", "dinov2-s")] + [row("smolvla", "libero_spatial", "siglip", 0, 1.0)]
    results = results_table(rows)
    siglip, dinov2, plain = results["run_id"].to_list()
    lines: list[str] = []
    chosen = select_rows(results, run_ids=[siglip, dinov2, plain], log=lines.append)
    assert sorted(chosen["run_id"].to_list()) == sorted([dinov2, plain])
    assert lines == [f"runs {siglip} are the policy of run {dinov2} (smolvla/dinov2-s/libero_spatial control "
                     "zero-image seed 0, policy 0123456789abcdef): rolled out once, as run " + dinov2]


def test_cameras_the_simulator_cannot_feed_are_refused_in_one_line() -> None:
    results = full_table().with_columns(camera_map=pl.lit("image=agentview,image2=eye_in_hand"))
    with pytest.raises(RolloutError) as refused:
        select_rows(results, top=1, suites=["libero_object"])
    line = str(refused.value)
    assert "\n" not in line and line.startswith("run ") and "/libero_object, control " in line
    assert line.endswith("its cache cameras agentview, eye_in_hand are not cameras the LIBERO simulator feeds "
                         "(image (agentview), image2 (wrist (eye in hand))); extract and fit it from a dataset whose "
                         "cameras are named image/image2")


def _request(tmp_path: Path, **over: Any) -> RolloutRequest:
    results = write_results(tmp_path / "results.parquet")
    fields = {"results": results, "rollouts": tmp_path / "rollouts.parquet", "top": 1, "suites": ("libero_object",),
              "tasks": (0, 3), "episodes_per_task": 2, "seed": 7, "command": "graftcache rollout results.parquet"}
    return RolloutRequest(**{**fields, **over})


def test_rows_are_typed_and_a_rerun_adds_nothing_and_says_so(tmp_path: Path) -> None:
    req = _request(tmp_path)
    lines: list[str] = []
    sim = Scripted()
    rows = rolled(req, sim, log=lines.append)
    # top 1 on libero_object: smolvla siglip and pi05 dinov2-s, 3 seeds each (no controls there): 6 cells x 2 tasks
    # x 2 episodes
    assert rows.height == len(sim.ran) == 24 and rows.schema == pl.Schema(rollouts_file.SCHEMA)
    first = rows.filter(pl.col("task_index") == 3, pl.col("episode") == 1).row(0, named=True)
    assert (first["suite"], first["seed"], first["init_state"], first["max_steps"]) == ("libero_object", 8, 1, 280)
    assert (first["success"], first["steps"], first["seconds"], first["video"]) == (True, 4, 0.5, None)
    assert first["lerobot_version"] == importlib.metadata.version("lerobot")
    assert first["command"] == "graftcache rollout results.parquet" and first["format_version"] == 3
    assert first["kernels"] == "scripted"  # the simulator's Outcome's, as it said them
    assert (first["target"], first["perturbation_m"], first["target_offset_x_m"], first["target_offset_y_m"]) == (
        "alphabet_soup_1", 0.0, 0.0, 0.0)  # official init states
    assert (first["min_target_distance_m"], first["final_target_distance_m"], first["target_lift_m"],
            first["grasped"], first["goal_fraction"]) == (0.2, 0.3, 0.0, True, 0.0)
    assert rows.group_by("run_id").len()["len"].to_list() == [4] * 6  # every cell on the same 4 episodes
    assert lines[0] == f"rolling out 6 cell(s), 24 episode(s) into {req.rollouts}"
    lines.clear()
    again = rolled(req, Scripted(), log=lines.append)
    assert lines == [f"all 24 episodes of 6 cell(s) are already in {req.rollouts}: nothing to run"]
    assert again.sort("episode_id").equals(rows.sort("episode_id"))
    assert rollouts_file.read(req.rollouts).height == 24
    more = rolled(_request(tmp_path, episodes_per_task=3), Scripted(), log=lines.append)
    assert more.height == 36 and f"24 of 36 episodes already in {req.rollouts}; running the other 12" in lines


def test_a_run_stopped_mid_way_resumes_to_the_same_rows(tmp_path: Path) -> None:
    for name in ("whole", "cut"):
        (tmp_path / name).mkdir()
    expected = rolled(_request(tmp_path / "whole"), Scripted(), log=lambda _: None)
    cut = _request(tmp_path / "cut")
    with pytest.raises(KeyboardInterrupt):
        rolled(cut, Scripted(stop_after=9), log=lambda _: None)
    assert rollouts_file.read(cut.rollouts).height == 9  # each finished episode was written as it finished
    sim = Scripted()
    resumed = rolled(cut, sim, log=lambda _: None)
    assert len(sim.ran) == 15
    drop = ["command"]
    assert resumed.drop(drop).sort("episode_id").equals(expected.drop(drop).sort("episode_id"))
    assert not claims_folder(cut.rollouts).exists()  # claims released, their folder gone


def _decoded(path: Path) -> tuple[int, float]:
    """An mp4's decoded frame count and frame rate."""
    import av

    with av.open(str(path)) as container:
        return sum(1 for _ in container.decode(video=0)), float(container.streams.video[0].average_rate)


def test_videos_are_written_whole_beside_the_rollouts_file_before_their_rows(tmp_path: Path) -> None:
    req = _request(tmp_path, tasks=(3,))
    run = select_rows(results.read(req.results), top=1, suites=["libero_object"])["run_id"][0]
    stale = tmp_path / "videos" / run / "libero_object_task3_ep1_seed8_max280.mp4"
    stale.parent.mkdir(parents=True)
    stale.write_bytes(b"a video a killed run wrote before its row")  # its row is missing: rerun, overwritten
    rows = rolled(req, Scripted(videos=True), log=lambda _: None)
    row = rows.filter(pl.col("run_id") == run, pl.col("episode") == 1).row(0, named=True)
    assert row["video"] == f"videos/{run}/libero_object_task3_ep1_seed8_max280.mp4"
    for r in rows.iter_rows(named=True):
        assert _decoded(tmp_path / r["video"]) == (r["steps"] + 1, 10.0)
    assert sorted(p.name for p in stale.parent.iterdir()) == ["libero_object_task3_ep0_seed7_max280.mp4",
                                                              "libero_object_task3_ep1_seed8_max280.mp4"]  # no temps


def test_a_task_the_suite_lacks_names_the_run_and_suite(tmp_path: Path) -> None:
    with pytest.raises(RolloutError, match=r"^run \w{16}: suite libero_object has tasks 0-9, not task 12$"):
        rolled(_request(tmp_path, tasks=(0, 12)), Scripted(), log=lambda _: None)
    assert not (tmp_path / "rollouts.parquet").exists()


def test_a_missing_simulator_is_one_line_naming_the_set_up(monkeypatch: pytest.MonkeyPatch) -> None:
    from graftcache.rollout.simulator_setup import require_simulator

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "libero" else real(name, *a))
    with pytest.raises(RolloutError) as refused:
        require_simulator()
    assert str(refused.value) == ("the LIBERO simulator is not installed (no Python module libero); run `make "
                                  "setup-libero` (scripts/setup.sh libero) to install it")


def test_a_failed_run_leaves_no_claims_folder(tmp_path: Path) -> None:
    class Broken(Scripted):
        def run(self, row: Mapping[str, Any], episodes: Sequence[Episode]) -> Iterator[Outcome]:
            yield from super().run(row, episodes[:1])
            raise RuntimeError("the simulator broke")

    req = _request(tmp_path)
    with pytest.raises(RuntimeError, match="the simulator broke"):
        rolled(req, Broken(), log=lambda _: None)
    assert rollouts_file.read(req.rollouts).height == 1  # the episode it finished
    assert not claims_folder(req.rollouts).exists()


def test_seeds_and_episode_counts_past_what_a_seed_holds_are_refused_before_any_episode(tmp_path: Path) -> None:
    """Episode k is seeded seed + k, an unsigned 32-bit seed for numpy and the simulator (2**40 reached set_seed's
    ValueError traceback); 10**9 episodes a task were listed and hashed one by one."""
    assert _request(tmp_path, seed=2**32 - 2, episodes_per_task=2).seed == 2**32 - 2  # seeds 2**32 - 2, 2**32 - 1
    with pytest.raises(RolloutError, match=r"^--seed 4294967294: episodes are seeded 4294967294 to 4294967296, which "
                                           r"must lie in 0 to 4294967295 \(an unsigned 32-bit seed\)$"):
        _request(tmp_path, seed=2**32 - 2, episodes_per_task=3)
    with pytest.raises(RolloutError, match=r"^--episodes-per-task 1000000000: must be 1 to 1000$"):
        _request(tmp_path, episodes_per_task=10**9)


def test_perturbed_episodes_are_other_episodes_recorded_in_their_rows(tmp_path: Path) -> None:
    """--perturb-cm 3: the same cells and seeds again, as new episodes (ids of their own, videos of their own), each
    row recording the largest offset asked and the one applied; the official-init rows keep their format-1 ids."""
    official = rolled(_request(tmp_path, tasks=(0,)), Scripted(), log=lambda _: None)
    lines: list[str] = []
    perturbed = rolled(_request(tmp_path, tasks=(0,), perturb_cm=3.0), Scripted(videos=True), log=lines.append)
    assert lines[0] == f"rolling out 6 cell(s), 12 episode(s) into {tmp_path / 'rollouts.parquet'}, targets slid up " \
                       "to 3 cm"
    assert perturbed.height == official.height == 12 and rollouts_file.read(tmp_path / "rollouts.parquet").height == 24
    assert set(perturbed["perturbation_m"].to_list()) == {0.03} and set(official["perturbation_m"]) == {0.0}
    assert set(zip(perturbed["target_offset_x_m"], perturbed["target_offset_y_m"], strict=True)) == {(0.015, -0.0075)}
    row = official.row(0, named=True)
    key = {k: row[k] for k in ("run_id", "suite", "task_index", "episode", "seed", "max_steps")}
    assert row["episode_id"] == hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()[:16]
    twin = perturbed.filter(pl.col("run_id") == row["run_id"], pl.col("episode") == row["episode"]).row(0, named=True)
    assert twin["episode_id"] == hashlib.sha256(json.dumps({**key, "perturbation_m": 0.03},
                                                           sort_keys=True).encode()).hexdigest()[:16]
    assert twin["video"] == f"videos/{row['run_id']}/libero_object_task0_ep{row['episode']}_seed{row['seed']}_max280" \
                            "_perturb0.03m.mp4"


def test_perturbations_past_10_cm_or_below_0_are_refused_in_one_line(tmp_path: Path,
                                                                     capsys: pytest.CaptureFixture) -> None:
    from helpers.probes import run_cli

    assert _request(tmp_path, perturb_cm=10.0).perturb_cm == 10.0
    for bad in (10.5, -0.5, float("nan")):
        with pytest.raises(RolloutError, match=rf"^--perturb-cm {bad}: must be 0 to 10 \(cm\)$"):
            _request(tmp_path, perturb_cm=bad)
    results_path = write_results(tmp_path / "results.parquet")
    for flag, said in (("-1", "'-1': must be a finite number of centimetres, 0 or more"),
                       ("inf", "'inf': must be a finite number of centimetres, 0 or more"),
                       ("3cm", "'3cm' is not a number")):
        refused = run_cli(["rollout", results_path, "--perturb-cm", flag], capsys)
        assert refused.code == 2 and refused.err.strip().endswith(f"argument --perturb-cm: {said}")
    past = run_cli(["rollout", results_path, "--perturb-cm", "12"], capsys)
    assert past.code == 2 and past.err.strip() == "graftcache rollout: error: --perturb-cm 12.0: must be 0 to 10 (cm)"


def test_the_reset_reaches_the_simulator_and_a_hard_rerun_of_soft_episodes_runs_none(
        tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """--reset soft (the default) and hard give the same episodes (tests/rollout/test_soft_reset.py), so a rerun
    with the other finds them all and runs none; the simulator is handed the reset asked; another is refused."""
    from helpers.probes import run_cli

    soft = Scripted()
    rows = rolled(_request(tmp_path), soft, log=lambda _: None)
    assert {e.reset for e in soft.ran} == {"soft"} and len(soft.ran) == rows.height == 24
    hard, lines = Scripted(), []
    again = rolled(_request(tmp_path, reset="hard"), hard, log=lines.append)
    assert hard.ran == [] and again.equals(rows) and lines[0].startswith("all 24 episodes of 6 cell(s) are already")
    (tmp_path / "rollouts.parquet").unlink()
    rolled(_request(tmp_path, reset="hard"), hard, log=lambda _: None)
    assert {e.reset for e in hard.ran} == {"hard"} and len(hard.ran) == 24
    with pytest.raises(RolloutError, match=r"^--reset warm: must be one of soft, hard$"):
        _request(tmp_path, reset="warm")
    refused = run_cli(["rollout", tmp_path / "results.parquet", "--reset", "warm"], capsys)
    assert refused.code == 2 and "argument --reset: invalid choice: 'warm'" in refused.err


def test_a_device_is_checked_before_any_simulator_starts(tmp_path: Path, capsys: pytest.CaptureFixture,
                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    """--device takes what the other commands take (cpu, cuda, cuda:N); one this machine lacks is refused in one line
    before the simulator's imports, with no rollouts file written."""
    import torch
    from helpers.probes import run_cli

    for device in ("cpu", "cuda", "cuda:1"):
        assert _request(tmp_path, device=device).device == device
    for device in ("tpu", "cuda:", "CPU", "cuda:0,1"):
        with pytest.raises(RolloutError, match=rf"^--device {device}: must be cpu, cuda or cuda:N$"):
            _request(tmp_path, device=device)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    monkeypatch.setattr("graftcache.rollout.libero.LiberoSimulator.__init__", None)  # never reached
    refused = run_cli(["rollout", tmp_path / "results.parquet", "--device", "cuda", "--top", "1"], capsys)
    assert refused.code == 2, refused.err
    assert refused.err.strip() == "graftcache rollout: error: --device cuda: CUDA is not available on this machine"
    assert not (tmp_path / "rollouts.parquet").exists()


def test_a_format_2_rollouts_file_reads_with_its_kernels_null(tmp_path: Path) -> None:
    """Rows written before rows recorded their policy's kernels (format 2) read with kernels null, everything else
    as written; a file mixing format 2 and 3 rows is not filled (its format-2 rows would have lost the column)."""
    path = tmp_path / "rollouts.parquet"
    row = {c: None for c in rollouts_file.SCHEMA if c != "kernels"}
    row.update(episode_id="0123456789abcdef", format_version=2, run_id="fedcba9876543210", suite="libero_object",
               task_index=0, episode=0, seed=1000, init_state=0, max_steps=60, success=False, steps=60, seconds=1.5,
               perturbation_m=0.0, lerobot_version="0.6.1", graftcache_version="0.1.0", command="graftcache rollout")
    schema = {c: t for c, t in rollouts_file.SCHEMA.items() if c != "kernels"}
    pl.DataFrame([row], schema=schema).write_parquet(path)
    rows = rollouts_file.read(path)
    assert rows.schema == pl.Schema(rollouts_file.SCHEMA) and rows["kernels"].to_list() == [None]
    assert {k: v for k, v in rows.row(0, named=True).items() if k != "kernels"} == row
    pl.DataFrame([row, {**row, "episode_id": "1111111111111111", "format_version": 3}],
                 schema=schema).write_parquet(path)
    with pytest.raises(RolloutError, match=r"missing \['kernels'\]"):
        rollouts_file.read(path)


def test_a_format_1_rollouts_file_reads_with_its_graded_columns_null(tmp_path: Path) -> None:
    """Rows written before graded progress (format 1: no target, perturbation or measures) read with those columns
    null and their ids unchanged, and a format-2 row appends beside them; a format-1 file missing another column is
    still refused."""
    path = tmp_path / "rollouts.parquet"
    old = {"episode_id": "0123456789abcdef", "format_version": 1, "run_id": "fedcba9876543210",
           "suite": "libero_object", "task_index": 0, "episode": 0, "seed": 1000, "init_state": 0, "max_steps": 60,
           "success": False, "steps": 60, "seconds": 120.5, "video": None, "lerobot_version": "0.6.1",
           "graftcache_version": "0.1.0", "command": "graftcache rollout results.parquet"}
    pl.DataFrame([old], schema_overrides={"video": pl.String}).write_parquet(path)
    rows = rollouts_file.read(path)
    assert rows.schema == pl.Schema(rollouts_file.SCHEMA) and rows.height == 1
    assert rows.select(rollouts_file.FORMAT_2_COLUMNS).row(0) == (None,) * 9
    assert {k: v for k, v in rows.row(0, named=True).items() if k in old} == old
    new = {**old, "episode_id": "1111111111111111", "format_version": 2, "target": "alphabet_soup_1",
           "perturbation_m": 0.0, "target_offset_x_m": 0.0, "target_offset_y_m": 0.0, "min_target_distance_m": 0.04,
           "final_target_distance_m": 0.2, "target_lift_m": 0.0, "grasped": False, "goal_fraction": 0.0}
    record.append(path, [new])
    both = rollouts_file.read(path).sort("format_version")
    assert both["min_target_distance_m"].to_list() == [None, 0.04] and both["target"].to_list() == [
        None, "alphabet_soup_1"]
    pl.DataFrame([old]).drop("seconds").write_parquet(path)
    with pytest.raises(RolloutError, match=r"^.*rollouts\.parquet: rollouts rows do not match the schema: missing "
                                           r"\['seconds'\], unexpected \[\]; pass another --rollouts$"):
        rollouts_file.read(path)


def test_the_files_are_checked_before_the_simulator_is_imported(tmp_path: Path, capsys: pytest.CaptureFixture,
                                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    """A missing results file, or a results file given as --rollouts, is one line at once (the simulator's imports
    took minutes before the first said "no plain-graft row", the second "rollouts rows of format 4")."""
    from helpers.probes import run_cli

    from graftcache.rollout import libero

    def no_simulator(*args: Any, **kwargs: Any) -> None:
        raise AssertionError("the simulator was started")

    monkeypatch.setattr(libero, "LiberoSimulator", no_simulator)
    missing = run_cli(["rollout", tmp_path / "nope.parquet"], capsys)
    assert missing.code == 2 and missing.err.strip() == (
        f"graftcache rollout: error: {tmp_path / 'nope.parquet'}: no results file (run `graftcache sweep` or "
        "`graftcache demo` first)")
    results_path = write_results(tmp_path / "results.parquet")
    swapped = run_cli(["rollout", results_path, "--rollouts", results_path], capsys)
    assert swapped.code == 2 and swapped.err.strip() == (
        f"graftcache rollout: error: {results_path}: a results table, not rollouts rows (no episode_id column); pass "
        "another --rollouts")


# train-tiny, extract, fit, four 10-step episodes (one perturbed), videos, one process: 155 s on 2 cores shared with
# 3 other jobs (load 4.7); 59 s on 2 idle cores before the graded columns and the perturbed episode
@pytest.mark.slow
def test_rollout_smoke_in_the_simulator(simulator_cells: Fitted, tmp_path: Path,
                                       capsys: pytest.CaptureFixture) -> None:
    """tiny policy -> extract -> fit two cells -> rollout of both in LIBERO (one process) with videos and graded
    progress -> the same command adds nothing -> a moved export runs there too, the same episode measuring the same,
    and a perturbed one (--perturb-cm 3) slides the target by its seeded draw -> report --rollouts with undefined
    agreement figures (every cell fails).

    Graded columns, against what is known of the scene: init state 0 of libero_object task 0 puts the end effector
    0.316 m from the alphabet soup after lerobot's reset (robosuite's observations: eef (-0.153, -0.006, 0.248),
    soup (-0.119, -0.240, 0.038)); 10 steps of OSC deltas move it at most ~1.5 cm each (the sample's saturated
    reach closes 0.21 m in 20 steps), so the closest approach lies between 0.15 m and that start, and nothing is
    grasped, lifted or placed."""
    from helpers.probes import run_cli
    from lerobot.envs.libero import LiberoEnv

    root, results_path, rollouts_path = simulator_cells.root, simulator_cells.results, tmp_path / "rollouts.parquet"
    a, b = sorted([simulator_cells.plain, simulator_cells.zero_image])
    rollout = ["rollout", results_path, "--run-ids", f"{a},{b}", "--suites", "libero_object", "--tasks", "0",
               "--episodes-per-task", "1", "--max-steps", "10", "--videos", "--cache", root, "--rollouts",
               rollouts_path]
    first = run_cli(rollout, capsys)
    assert first.code == 0, first.err[-3000:]
    rows = rollouts_file.read(rollouts_path).sort("run_id")
    assert rows["run_id"].to_list() == sorted([a, b])
    for r in rows.iter_rows(named=True):
        assert (r["suite"], r["task_index"], r["episode"], r["seed"], r["init_state"]) == ("libero_object", 0, 0,
                                                                                          1000, 0)
        assert r["max_steps"] == 10 and (r["steps"] == 10 or r["success"]) and r["seconds"] > 0
        assert r["lerobot_version"] == importlib.metadata.version("lerobot")
        # lerobot's rollout renders after the reset and after each step, at the env's render_fps
        assert r["video"] == f"videos/{r['run_id']}/libero_object_task0_ep0_seed1000_max10.mp4"
        assert _decoded(tmp_path / r["video"]) == (r["steps"] + 1, LiberoEnv.metadata["render_fps"])
        assert (r["target"], r["perturbation_m"], r["target_offset_x_m"], r["target_offset_y_m"]) == (
            "alphabet_soup_1", 0.0, 0.0, 0.0)
        assert 0.15 < r["min_target_distance_m"] <= 0.3165 and r["final_target_distance_m"] >= r[
            "min_target_distance_m"]
        assert r["target_lift_m"] < 0.005 and (r["grasped"], r["goal_fraction"]) == (False, 0.0)
    assert all((tmp_path / "exports" / run / "config.json").is_file() for run in (a, b))

    # a moved export runs through lerobot-eval's loading and rollout as it ran in place (it named its own absolute
    # path in its preprocessor before, and failed on its first observation)
    from graftcache.rollout.libero import LiberoSimulator
    from graftcache.rollout.perturb import offsets, rng_of

    moved = tmp_path / "moved" / "exports"
    moved.parent.mkdir()
    (tmp_path / "exports").rename(moved)
    sim = LiberoSimulator(results_path, moved, cache=str(root), runs=None, max_steps=10)
    try:
        cell = results.read(results_path).filter(pl.col("run_id") == a).row(0, named=True)
        outcome, slid = sim.run(cell, [Episode(a, "libero_object", 0, 0, 1000, 10),
                                       Episode(a, "libero_object", 0, 0, 1000, 10, perturbation_m=0.03)])
    finally:
        sim.close()
    ran = rows.filter(pl.col("run_id") == a).row(0, named=True)
    assert (outcome.success, outcome.steps, outcome.init_state) == (ran["success"], ran["steps"], 0)
    assert outcome.graded == Graded(**{k: pytest.approx(ran[k], abs=1e-6) if isinstance(ran[k], float) else ran[k]
                                       for k in ("target", "min_target_distance_m", "final_target_distance_m",
                                                 "target_lift_m", "grasped", "goal_fraction")})
    # the perturbed episode: the first of its seeded draws that settled (seed 1000, task 0: (+0.13, +0.62) cm)
    assert outcome.target_offset_m == (0.0, 0.0) and slid.target_offset_m in [
        tuple(d) for d in offsets(rng_of(1000, 0), 0.03)]
    assert slid.graded.min_target_distance_m != outcome.graded.min_target_distance_m
    assert sorted(p.name for p in moved.iterdir()) == sorted([a, b])  # used where it is, not exported again

    again = run_cli(rollout, capsys)
    assert again.code == 0, again.err[-2000:]
    assert f"all 2 episodes of 2 cell(s) are already in {rollouts_path}: nothing to run" in again.out
    assert rollouts_file.read(rollouts_path).sort("run_id").equals(rows)

    out = tmp_path / "report"
    shown = run_cli(["report", results_path, "--out", out, "--rollouts", rollouts_path], capsys)
    assert shown.code == 0, shown.err[-2000:]
    assert "## Offline scores vs closed-loop success" in (out / "report.md").read_text()
    csv = pl.read_csv(out / "closed_loop.csv").filter(pl.col("measure") == "success")
    mse = csv.filter(pl.col("score") == "eval_mse", pl.col("cells_of") == "with controls").row(0, named=True)
    assert (mse["backbone"], mse["suite"], mse["cells"]) == ("smolvla", "libero_object", 2)  # plain and zero-image
    assert csv.height == 8 and csv.select("spearman", "kendall_tau_b", "mmrv").null_count().row(0) == (8, 8, 8)
    assert ("smolvla,libero_object,with controls,eval_mse,success,2" + "," * 10 + "\n"
            in (out / "closed_loop.csv").read_text())


def test_a_suite_or_task_or_perturbation_it_cannot_run_is_refused_before_the_simulator(
        tmp_path: Path, capsys: pytest.CaptureFixture, monkeypatch: pytest.MonkeyPatch) -> None:
    """`--suites nope` is "not a LIBERO suite" (it was "no plain-graft row ... to rank"), a task past the suite's
    and a perturbation finer than its resolution are refused before the team and the simulator start (the first two
    came after ~14 s of simulator imports, 1e-300 cm made 'perturbed' episodes of the official scenes)."""
    from helpers.probes import run_cli

    from graftcache.rollout import roll_out as rollout_run

    def started(*args: object, **kwargs: object) -> None:
        raise AssertionError("the simulator was started")

    monkeypatch.setattr(rollout_run, "roll_out_started", started)
    results_path = write_results(tmp_path / "results.parquet")
    run_id = select_rows(full_table(), top=1, suites=["libero_spatial"])["run_id"][0]
    for flags, said in ((["--suites", "libero_spatial,nope"], "--suites nope: not a LIBERO suite (libero_spatial, "
                         "libero_object, libero_goal, libero_10, libero_90)"),
                        (["--suites", "libero_spatial", "--top", "1", "--tasks", "3,10"],
                         f"run {run_id}: suite libero_spatial has tasks 0-9, not task 10"),
                        (["--perturb-cm", "1e-300"], "--perturb-cm 1e-300: finer than its resolution, 0.01 cm (0: "
                         "none)"),
                        (["--perturb-cm", "3.004"], "--perturb-cm 3.004: finer than its resolution, 0.01 cm (0: "
                         "none)")):
        refused = run_cli(["rollout", results_path, *flags], capsys)
        assert (refused.code, refused.err) == (2, f"graftcache rollout: error: {said}\n"), flags
    assert _request(tmp_path, perturb_cm=0.07).perturb_cm == 0.07 and _request(tmp_path, perturb_cm=3).perturb_cm == 3
