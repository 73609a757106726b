"""`graftcache demo --closed-loop`: the demo's cells in the LIBERO simulator, enough of them, on scenes that make
the policy look, for the report's first measured offline-vs-closed-loop figure.

Success is 0% for everything trainable on the bundled sample, so the figure rests on graded progress read from the
simulator's state (graftcache.rollout.graded): how close the end effector comes to the task's target. What runs
(CLOSED_LOOP, each number with its reason):

- the demo recipe (cli/demo.toml) with more seeds and without the shuffled-image control, which has no closed-loop
  meaning, into its own results file beside the demo's (the demo's report keeps its own rows);
- on the figure's (backbone, suite): every row, so the agreement of eval_mse with closed-loop progress rests on
  encoders x seeds plus native-graft and zero-image (>= 24 cells); on the other (backbone, suite)s: the native tower
  against the top encoder's zero-image control of the paired seeds, the check that looking helps in closed loop;
- each policy once (graftcache.rollout.select.one_per_policy: one run_id per policy_id, the lowest seed's, then the
  first encoder's by name): the native tower trains nothing, so its rows of every seed are one policy, and the
  zero-image rows of one seed are one policy whatever the encoder (their features are zeroed and their caches hold
  the same frames); rolled out again they would be the same episodes counted again;
- the paired cells on twice the episodes of the figure's: the figure's agreement rests on 29 cells, the paired check
  on one native cell against two zero-image cells, so its power comes from paired episodes alone. Measured on the
  first run of this demo (2026-11-28): tiny pi0.5 on libero_object, 4 episodes, native minus zero-image closest
  approach -0.061 m [-0.166, +0.001], not separated; its 8 episodes, -0.050 [-0.106, -0.011] (-0.048 [-0.099,
  -0.013] on the refitted cells the README quotes). The other three (backbone, suite)s were separated on 4;
- every episode on a perturbed scene: libero_object's official init states place the target identically, so a
  policy blind to its cameras could still reach it; the sample's own perturbation (data/render_sample.py, 3 cm) is
  what made its actions depend on the images.

Then the report, with the rollouts, beside the results.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import polars as pl

from graftcache.analysis import NATIVE_CONTROL, ZERO_IMAGE
from graftcache.demo import DEFAULT_RECIPE
from graftcache.errors import GraftcacheError
from graftcache.fit.controls import get_control
from graftcache.progress import write
from graftcache.recipe import load_recipe
from graftcache.report import ReportPaths, write_report
from graftcache.results import read_for_report
from graftcache.rollout.select import select_rows
from graftcache.store import cache_root
from graftcache.sweep import run_sweep


@dataclass(frozen=True)
class ClosedLoopPlan:
    """What `demo --closed-loop` fits and rolls out on top of the demo recipe."""

    #: four seeds: with three encoders, 12 plain and 12 zero-image cells on the figure's (backbone, suite)
    seeds: tuple[int, ...] = (0, 1, 2, 3)
    controls: tuple[str, ...] = ("native", "native-graft", "zero-image")
    results: str = "demo/closed_loop/results.parquet"
    #: where every cell runs: tiny SmolVLA on libero_object, the faster suite to simulate (0.2 s a step against
    #: libero_spatial's 0.4, 2-core AMD EPYC)
    figure: tuple[str, str] = ("smolvla", "libero_object")
    #: the seeds whose zero-image rows face the native tower on the other (backbone, suite)s: the demo's own
    paired_seeds: tuple[int, ...] = (0, 1)
    tasks: tuple[int, ...] = (0,)
    episodes_per_task: int = 4
    #: the paired cells' episodes (episode k from init state k: their first `episodes_per_task` are the figure's)
    paired_episodes_per_task: int = 8
    #: the sample's own planar target jitter, m per axis (data/render_sample.py --jitter)
    perturb_cm: float = 3.0
    #: the sample's demonstrations reach, descend, grasp and lift in 46-56 frames (render_manifest.json); by 40 steps
    #: a policy that learned them has reached and closed on the target
    max_steps: int = 40
    workers: int = 2


CLOSED_LOOP = ClosedLoopPlan()


@dataclass(frozen=True)
class ClosedLoopCells:
    """The run_ids `demo --closed-loop` rolls out: the figure's cells, on `episodes_per_task` episodes, and the
    other (backbone, suite)s' paired cells, on `paired_episodes_per_task`."""

    figure: tuple[str, ...]
    paired: tuple[str, ...]


def closed_loop_run_ids(results: pl.DataFrame, plan: ClosedLoopPlan = CLOSED_LOOP,
                        log: Callable[[str], None] = write) -> ClosedLoopCells:
    """The cells `demo --closed-loop` rolls out of `results` (see the module docstring): on the figure's
    (backbone, suite), every row with a closed-loop meaning (not shuffled-image: graftcache.fit.controls), one per
    policy; on the others, native and the top encoder's zero-image rows of `paired_seeds`. A figure's
    (backbone, suite) missing from `results` is an error: there would be no figure. Which run stands for a policy
    of several is said in `log`."""
    backbone, suite = plan.figure
    live = results.filter(pl.col("control").map_elements(lambda c: get_control(c).closed_loop, pl.Boolean))
    figure = live.filter((pl.col("backbone") == backbone) & (pl.col("suite") == suite))
    if not figure.height:
        raise GraftcacheError(f"no row of {backbone} on {suite} in the results: the closed-loop figure has no cells")
    others = live.join(figure.select("run_id"), on="run_id", how="anti")
    paired = (select_rows(others, top=1, log=log).filter(pl.col("control").is_in([NATIVE_CONTROL, ZERO_IMAGE])
                                                        & pl.col("seed").is_in(list(plan.paired_seeds)))
              if others.height else others)
    chosen = select_rows(figure, run_ids=figure["run_id"].to_list(), log=log)
    return ClosedLoopCells(figure=tuple(chosen["run_id"].to_list()), paired=tuple(paired["run_id"].to_list()))


def run_closed_loop_demo(recipe_path: str | Path | None = None, out: str | Path | None = None,
                         plan: ClosedLoopPlan = CLOSED_LOOP) -> ReportPaths:
    """Fit the plan's cells (resumable), roll out its episodes (resumable), and write the report with them."""
    from graftcache.executors import get_executor
    from graftcache.requests import ExecutorSettings
    from graftcache.rollout.libero import LiberoSimulator, require_simulator
    from graftcache.rollout.run import EXPORTS_FOLDER, RolloutRequest, default_rollouts, roll_out_started

    require_simulator()  # before minutes of fitting
    path = Path(recipe_path) if recipe_path else DEFAULT_RECIPE
    if not path.is_file():
        raise GraftcacheError(f"{path}: demo recipe not found (run from a checkout of graftcache, or pass --recipe)")
    t0 = time.perf_counter()
    recipe = load_recipe(path)
    results = cache_root(recipe.cache) / plan.results
    recipe = dataclasses.replace(recipe, seeds=plan.seeds, controls=plan.controls, results=str(results))
    state = run_sweep(recipe)
    cells = closed_loop_run_ids(read_for_report(results), plan)
    rollouts = default_rollouts(results)
    command = f"graftcache demo --closed-loop --recipe {path}"
    spawn = partial(LiberoSimulator, results, rollouts.parent / EXPORTS_FOLDER, cache=recipe.cache, runs=None,
                    max_steps=plan.max_steps)
    requests = [RolloutRequest(results=results, rollouts=rollouts, run_ids=run_ids, tasks=plan.tasks,
                               episodes_per_task=episodes, max_steps=plan.max_steps, perturb_cm=plan.perturb_cm,
                               command=command)
                for run_ids, episodes in ((cells.figure, plan.episodes_per_task),
                                          (cells.paired, plan.paired_episodes_per_task))]
    # one team for both: its workers start first, their simulators building while this process builds its own, to plan
    team = get_executor(ExecutorSettings()).rollout_team(requests[0], spawn, plan.workers, write)
    roll_out_started(requests, spawn, team)
    report_dir = Path(out) if out else results.parent / "report"
    commands = {"demo --closed-loop": command, **state.commands}
    paths = write_report(results, report_dir, commands=commands, rollouts=rollouts)
    write(f"closed-loop demo finished in {time.perf_counter() - t0:.0f}s")
    return paths
