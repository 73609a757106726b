"""`graftcache demo --closed-loop`: its choice of cells (graftcache/demo_closed_loop.py), on tests/helpers/tables.py's
hand-built results with native repeats and pi05 zero-image rows added; and what its report finds on the demo's own
rows (tests/fixtures/closed_loop_demo/), pinned. The command itself (fits, then minutes in the simulator) is measured
by hand and quoted in docs/closed-loop.md, not run in CI; its pieces (rollout, graded progress, workers, report) are
tested in tests/rollout and tests/report, and its rollout wiring by a rerun over its own rows that must run nothing."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import shutil
from collections.abc import Iterator
from pathlib import Path
from types import SimpleNamespace

import polars as pl
import pytest
from helpers.tables import control_rows, plain_rows, row, table
from scipy import stats

from graftcache import analysis as A
from graftcache.analysis.rollouts import PAIR_KEY
from graftcache.demo import DEFAULT_RECIPE
from graftcache.demo_closed_loop import CLOSED_LOOP, ClosedLoopDemo, closed_loop_run_ids
from graftcache.errors import GraftcacheError
from graftcache.results import read_for_report
from graftcache.rollout.episodes import Suite

DEMO = ClosedLoopDemo(figure=("smolvla", "libero_spatial"), paired_seeds=(0, 1))


def _one_policy_per_seed(r: dict) -> dict:
    """A zero-image row as format 6 writes it: one policy per (backbone, suite, seed) whatever the encoder (its
    features zeroed, its cache's frames those of every encoder's cache)."""
    if r["control"] == "zero-image":
        r["policy_id"] = hashlib.sha256(f"{r['backbone']} {r['suite']} {r['seed']}".encode()).hexdigest()[:16]
    return r


def _results() -> pl.DataFrame:
    native_repeats = [row("smolvla", "libero_spatial", "smolvla-native", s, 1.0, control="native") for s in (1, 2)]
    pi05_zero = [row("pi05", "libero_spatial", "dinov2-s", s, 4.0, control="zero-image") for s in (0, 1, 2)]
    return table([_one_policy_per_seed(r) for r in plain_rows() + control_rows() + native_repeats + pi05_zero])


def test_every_live_cell_of_the_figure_and_native_against_zero_image_elsewhere() -> None:
    """Each policy once: native of seed 0 alone (its rows of every seed are one policy: the upgrade's policy_id of a
    cell that trains nothing), and of the zero-image rows of siglip and resnet18 (one policy per seed) resnet18's,
    the first encoder by name; each choice said in one line."""
    results = _results()
    lines: list[str] = []
    cells = closed_loop_run_ids(results, DEMO, lines.append)
    chosen = results.filter(pl.col("run_id").is_in([*cells.figure, *cells.paired]))
    keys = set(chosen.select("backbone", "suite", "encoder", "control", "seed").rows())
    paired = results.filter(pl.col("run_id").is_in(cells.paired))
    figure = results.filter((pl.col("backbone") == "smolvla") & (pl.col("suite") == "libero_spatial"))
    expected_figure = {k for k in figure.select("backbone", "suite", "encoder", "control", "seed").rows()
                       if k[3] != "shuffled-image" and not (k[3] == "native" and k[4] > 0)
                       and not (k[3] == "zero-image" and k[2] == "siglip")}
    # pi05/libero_spatial: its best encoder is dinov2-s (1.4 < siglip 1.5): its zero-image rows of seeds 0 and 1
    expected_others = {("pi05", "libero_spatial", "pi05-native", "native", 0),
                       ("pi05", "libero_spatial", "dinov2-s", "zero-image", 0),
                       ("pi05", "libero_spatial", "dinov2-s", "zero-image", 1)}
    assert keys == expected_figure | expected_others
    assert set(paired.select("backbone", "suite", "encoder", "control", "seed").rows()) == expected_others
    assert not set(cells.figure) & set(cells.paired)
    assert len(expected_figure) == 3 * 3 + 3 + 3 + 1  # 3 encoders, zero-image, native-graft x 3 seeds; native
    assert chosen.height == len(keys)  # each once
    zero = results.filter((pl.col("control") == "zero-image") & (pl.col("suite") == "libero_spatial")
                          & (pl.col("backbone") == "smolvla")).sort("seed", "encoder")
    for seed in range(3):
        first, other = zero.filter(pl.col("seed") == seed)["run_id"].to_list()  # resnet18's, siglip's
        assert sum(line.startswith(f"runs {other} are the policy of run {first} (smolvla/resnet18/libero_spatial "
                                   f"control zero-image seed {seed}, ") for line in lines) == 1
    native = results.filter((pl.col("control") == "native") & (pl.col("backbone") == "smolvla")).sort("seed")
    assert any(line.startswith(f"runs {', '.join(native['run_id'][1:])} are the policy of run {native['run_id'][0]} ")
               for line in lines)


def test_a_figure_without_rows_is_refused() -> None:
    with pytest.raises(GraftcacheError, match="no row of smolvla on libero_90"):
        closed_loop_run_ids(_results(), ClosedLoopDemo(figure=("smolvla", "libero_90")))


def test_the_dose_recipe_is_the_figure_s_backbone_suite_and_dose_encoder() -> None:
    from graftcache.demo_closed_loop import _dose_recipe
    from graftcache.recipe import load_recipe

    recipe = load_recipe(DEFAULT_RECIPE)
    dose = _dose_recipe(recipe, CLOSED_LOOP)
    assert ([b.name for b in dose.backbones], [e.name for e in dose.encoders], dose.suites) == (
        ["smolvla"], ["efficientnet-lite0"], ("libero_object",))
    assert dose.controls == ("noise-0.25", "noise-0.5", "noise-0.75", "noise-0.9") and dose.seeds == recipe.seeds
    with pytest.raises(GraftcacheError, match="no backbone smolvla or no encoder dinov2-s: the dose family"):
        _dose_recipe(recipe, ClosedLoopDemo(dose_encoder="dinov2-s"))


# ------------------------------------------------------------------------------ the closed-loop demo's own rows
#: `make demo-closed-loop`'s results.parquet, rollouts.parquet and sequential.json as written (from scratch after
#: `make demo`, a 2-core Intel Xeon with avx512_bf16: docs/closed-loop.md quotes the run), read as the report reads them
DEMO_ROWS = Path(__file__).parent / "fixtures" / "closed_loop_demo"
FIGURE = ("smolvla", "libero_object")
VIT = "timm:vit_tiny_patch16_224"


@pytest.fixture(scope="module")
def demo() -> tuple[pl.DataFrame, pl.DataFrame, A.Analysis]:
    table = read_for_report(DEMO_ROWS / "results.parquet")
    rollouts = A.read_rollouts(DEMO_ROWS / "rollouts.parquet", table)
    return table, rollouts, A.analyze(table, rollouts=rollouts, looks=A.read_looks(DEMO_ROWS / "rollouts.parquet"))


def _figure(frame: pl.DataFrame) -> pl.DataFrame:
    return frame.filter(pl.col("backbone") == FIGURE[0], pl.col("suite") == FIGURE[1])


def test_the_demo_counts_each_policy_once(demo: tuple) -> None:
    """The figure's zero-image rows: 3 encoders x 4 seeds, one policy per seed (12 rows, 4 policies); native: 4
    rows, one policy; so the closed-loop cells are 12 candidates + 4 zero-image + 4 native-graft + 1 native + 4
    doses x 4 seeds = 37; each policy was rolled out under one of its run_ids, so no episode repeats."""
    table, rollouts, a = demo
    rows = _figure(table)
    zero = rows.filter(pl.col("control") == "zero-image")
    assert zero.height == 12 and zero.group_by("seed").agg(pl.col("policy_id").n_unique())["policy_id"].to_list() \
        == [1, 1, 1, 1]
    assert rows.filter(pl.col("control") == "native")["policy_id"].n_unique() == 1
    cells = _figure(a.closed_loop.cells)
    counts = dict(cells.group_by("control").len().iter_rows())
    assert counts == {"none": 12, "zero-image": 4, "native-graft": 4, "native": 1, "noise-0.25": 4, "noise-0.5": 4,
                      "noise-0.75": 4, "noise-0.9": 4}
    episodes = a.closed_loop.rollouts
    assert episodes.height == episodes.unique(["policy_key", *PAIR_KEY]).height == rollouts.height
    ran = rollouts.join(table.select("run_id", "policy_id"), on="run_id")  # each policy under one run_id
    assert ran.group_by("policy_id").agg(pl.col("run_id").n_unique())["run_id"].max() == 1


def test_the_demo_s_agreements_hold_their_figures(demo: tuple) -> None:
    """Candidates (12 plain grafts): Spearman +0.39, its interval reaching below 0 (offline MSE does not order the
    encoders beyond doubt); with controls (37 policies): +0.51, its interval above 0. Each interval holds its
    figure, and the candidates' Spearman is scipy's over the cells' eval_mse and mean closest approach."""
    _, _, a = demo
    agreement = _figure(a.closed_loop.agreement).filter(pl.col("score") == "eval_mse",
                                                        pl.col("measure") == "min_target_distance_m")
    got = {r["cells_of"]: r for r in agreement.iter_rows(named=True)}
    cand, ctrl = got[A.CANDIDATES], got[A.WITH_CONTROLS]
    assert (cand["cells"], ctrl["cells"]) == (12, 37)
    plain = _figure(a.closed_loop.cells).filter(pl.col("control") == "none")
    rho = stats.spearmanr(plain["eval_mse"], plain["min_target_distance_m"]).statistic  # oriented: + is agreement
    assert cand["spearman"] == pytest.approx(rho) and round(rho, 2) == 0.39
    assert cand["spearman_low"] < 0 < cand["spearman"] and round(ctrl["spearman"], 2) == 0.51
    assert ctrl["spearman_low"] > 0
    for r in (cand, ctrl):
        for name in ("spearman", "kendall_tau_b", "mmrv"):
            assert r[f"{name}_low"] <= r[name] <= r[f"{name}_high"]


def test_the_demo_s_pairwise_verdicts(demo: tuple) -> None:
    """On the figure's (backbone, suite): efficientnet-lite0 beats the random-init ViT offline and in closed loop
    (agree), mobilenetv2 beats it in both after the second look (agree, 32 pairs), and efficientnet-lite0 beats
    mobilenetv2 in closed loop only; each closed-loop side recomputed here from the episodes, paired by fit seed
    and episode key, with scipy's t interval at the looks' level (97.5%)."""
    table, _, a = demo
    pairs = _figure(a.closed_loop.pairwise).filter(pl.col("measure") == "min_target_distance_m")
    verdicts = {(r["encoder_a"], r["encoder_b"]): (r["offline"], r["closed"], r["verdict"], r["pairs"])
                for r in pairs.iter_rows(named=True)}
    assert verdicts == {("efficientnet-lite0", "mobilenetv2"): ("not resolved", "a", "closed loop only", 16),
                        ("efficientnet-lite0", VIT): ("a", "a", "agree", 16),
                        ("mobilenetv2", VIT): ("a", "a", "agree", 32)}
    assert a.closed_loop.looks.level == pytest.approx(0.975) and len(a.closed_loop.looks.looks) == 2
    plain = _figure(table).filter(pl.col("control") == "none").select("run_id", "encoder", pl.col("seed").alias("fit"))
    episodes = pl.read_parquet(DEMO_ROWS / "rollouts.parquet").join(plain, on="run_id")
    key = ["fit", "task_index", "episode", "seed", "perturbation_m"]
    for r in pairs.iter_rows(named=True):
        side = [episodes.filter(pl.col("encoder") == e).select(*key, pl.col("min_target_distance_m").alias(e))
                for e in (r["encoder_a"], r["encoder_b"])]
        both = side[0].join(side[1], on=key)
        diffs = (both[r["encoder_a"]] - both[r["encoder_b"]]).to_numpy()
        low, high = stats.t.interval(0.975, len(diffs) - 1, loc=diffs.mean(), scale=stats.sem(diffs))
        assert len(diffs) == r["pairs"] and r["closed_difference"] == pytest.approx(diffs.mean())
        assert (r["closed_low"], r["closed_high"]) == pytest.approx((low, high))
    summary = A.pairwise_summary(pairs).row(0, named=True)
    assert (summary["encoder_pairs"], summary["resolved_by_both"], summary["agree"]) == (3, 2, 2)


def test_the_demo_s_dose_resolution(demo: tuple) -> None:
    """efficientnet-lite0's dose curve on the figure: the closed loop confirms only the steps 0.75 -> 0.9 and
    0.9 -> 1 (zero-image), so the resolution is the offline gap of the first, about 0.058 eval_mse."""
    _, _, a = demo
    steps = a.dose.steps.filter(pl.col("confirmed"))
    assert [(r["dose_from"], r["dose_to"]) for r in steps.iter_rows(named=True)] == [(0.75, 0.9), (0.9, 1.0)]
    curve = a.dose.curves.row(0, named=True)
    assert curve["resolution"] == pytest.approx(steps["offline_diff"].min()) and round(curve["resolution"], 3) == 0.058


def test_the_demo_s_figure_names_every_marker_it_draws(demo: tuple) -> None:
    """The validity figure's legend names the three encoders, the native tower, native-graft and zero-image, and the
    doses' triangles (noise-A cells, in their encoder's colour); the candidates' panels of the (backbone, suite)s
    without rolled-out plain grafts are blank, saying so."""
    from graftcache.report.closed_loop_figure import figure_closed_loop

    fig = figure_closed_loop(demo[2])
    labels = [t.get_text() for t in fig.legends[0].get_texts()]
    assert labels[:3] == ["efficientnet-lite0", "mobilenetv2", VIT]
    assert labels[-1] == "other controls (noise-0.25, noise-0.5, noise-0.75, ...), in their encoder's colour"
    assert len(labels) == 7
    blank = [t.get_text() for ax in fig.axes if not ax.axison for t in ax.texts]
    assert sorted(blank) == ["SmolVLA · libero_spatial\nno candidates cell rolled out",
                             "pi0.5 · libero_object\nno candidates cell rolled out",
                             "pi0.5 · libero_spatial\nno candidates cell rolled out"]


class _Recorded:
    """The LIBERO simulator's stand-in for a rerun of the demo: what a suite is (the demo's step limit, as
    LiberoSimulator built with `max_steps` says), and every episode it is asked to run, counted (none may be)."""

    ran: list = []

    def __init__(self, *args: object, max_steps: int, **kwargs: object) -> None:
        self.max_steps = max_steps

    def suite(self, name: str) -> Suite:
        return Suite(n_tasks=10, max_steps=self.max_steps)

    def run(self, row: dict, episodes: list) -> Iterator:
        _Recorded.ran += episodes
        return iter(())


@pytest.mark.slow
def test_a_rerun_over_the_demo_s_own_rows_runs_no_episode_and_looks_as_it_did(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The command's rollout wiring (its two selections from one results read, the figure's sequential looks, one
    team for both) over the demo's recorded rows: every episode each look asks for is in the rollouts file, so the
    rerun runs none and decides its looks as the first run did (the record beside the file unchanged), and the report
    is written from the same files. The fits are the sweep's, which resumes from the results file (tests/test_sweep.py);
    here the sweep is skipped."""
    import graftcache.demo_closed_loop as demo_module
    from graftcache.rollout import libero, simulator_setup

    home = tmp_path / "home"
    monkeypatch.setenv("GRAFTCACHE_HOME", str(home))
    folder = (home / CLOSED_LOOP.results).parent
    folder.mkdir(parents=True)
    for name in ("results.parquet", "rollouts.parquet", "sequential.json"):
        shutil.copyfile(DEMO_ROWS / name, folder / name)
    before = {name: (folder / name).read_bytes() for name in ("results.parquet", "rollouts.parquet")}
    looks_before = json.loads((folder / "sequential.json").read_text())
    reports: list[dict] = []
    monkeypatch.setattr(demo_module, "run_sweep", lambda recipe: SimpleNamespace(commands={}))
    monkeypatch.setattr(demo_module, "write_report", lambda results, out, **kw: reports.append(
        {"results": results, "out": out, **kw}) or "paths")
    monkeypatch.setattr(simulator_setup, "require_simulator", lambda: None)
    monkeypatch.setattr(libero, "LiberoSimulator", _Recorded)
    _Recorded.ran = []

    paths = demo_module.run_closed_loop_demo(out=tmp_path / "report",
                                             demo=dataclasses.replace(CLOSED_LOOP, workers=1))
    assert paths == "paths" and _Recorded.ran == []
    assert {name: (folder / name).read_bytes() for name in before} == before
    looks_after = json.loads((folder / "sequential.json").read_text())
    assert looks_after.pop("command").endswith("--recipe " + str(DEFAULT_RECIPE))  # where this checkout's recipe is
    assert looks_after == {k: v for k, v in looks_before.items() if k != "command"}
    assert [(r["results"], r["out"], r["rollouts"]) for r in reports] == [
        (folder / "results.parquet", tmp_path / "report", folder / "rollouts.parquet")]
