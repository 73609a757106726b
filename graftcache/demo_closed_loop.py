"""`graftcache demo --closed-loop`: the demo's cells in the LIBERO simulator, enough of them, on scenes that make
the policy look, to say which encoder wins in closed loop, whether offline MSE picks it, and what offline gap the
closed loop can resolve at all.

Success is 0% for everything trainable on the bundled sample, so the figures rest on graded progress read from the
simulator's state (graftcache.rollout.graded): how close the end effector comes to the task's target. What runs
(CLOSED_LOOP, each number with its reason):

- the demo recipe (cli/demo.toml) with more seeds and without the shuffled-image control, which has no closed-loop
  meaning, into its own results file beside the demo's (the demo's report keeps its own rows);
- the dose family on the figure's (backbone, suite) (graftcache.fit.dose): one real-weights encoder's features
  degraded in four known steps between the encoder and the blind policy, every seed, fitted after the sweep; the
  report draws offline MSE and closed-loop progress against the dose and states the finest offline gap the closed
  loop confirms (graftcache.analysis.dose);
- on the figure's (backbone, suite): every row with a closed-loop meaning, so the candidates' agreement rests on
  encoders x seeds and the agreement with controls on native-graft, zero-image, native and the doses too; on the
  other (backbone, suite)s: the native tower against the top encoder's zero-image control of the paired seeds, the
  check that looking helps in closed loop;
- each policy once (graftcache.rollout.select.one_per_policy: one run_id per policy_id, the lowest seed's, then the
  first encoder's by name): the native tower trains nothing, so its rows of every seed are one policy, and the
  zero-image rows of one seed are one policy whatever the encoder (their features are zeroed and their caches hold
  the same frames); rolled out again they would be the same episodes counted again;
- the figure's cells in sequential looks (graftcache.rollout.sequential): `episodes_per_task` each, then as many
  again for the candidate pairs whose closed-loop order is still unresolved, up to `until_resolved`, so episodes go
  where they decide a pairwise verdict (the report states the error rate the looks hold);
- the paired cells on twice the figure's first look: the paired check rests on one native cell against two
  zero-image cells, so its power comes from paired episodes alone (docs/closed-loop.md, "The closed-loop demo",
  has the measurements behind the count);
- every episode on a perturbed scene: libero_object's official init states place the target identically, so a
  policy blind to its cameras could still reach it; the sample's own perturbation (data/render_sample.py, 3 cm) is
  what made its actions depend on the images.

Then the report, with the rollouts, beside the results.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import polars as pl

from graftcache.analysis import NATIVE_CONTROL, ZERO_IMAGE
from graftcache.demo import DEFAULT_RECIPE
from graftcache.errors import GraftcacheError
from graftcache.fit.controls import get_control
from graftcache.progress import write
from graftcache.recipe import Recipe, load_recipe
from graftcache.report import ReportPaths, write_report
from graftcache.results import read_for_report
from graftcache.rollout.select import select_rows
from graftcache.store import cache_root
from graftcache.sweep import run_sweep


@dataclass(frozen=True)
class ClosedLoopDemo:
    """What `demo --closed-loop` fits and rolls out on top of the demo recipe."""

    #: four seeds: with three encoders, 12 candidate cells (6 pairs of fit seed x encoder pair a seed's episodes pair)
    #: and 4 zero-image policies on the figure's (backbone, suite)
    seeds: tuple[int, ...] = (0, 1, 2, 3)
    controls: tuple[str, ...] = ("native", "native-graft", "zero-image")
    results: str = "demo/closed_loop/results.parquet"
    #: where every cell runs: tiny SmolVLA on libero_object, the faster suite to simulate (benchmarks/results)
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
    #: the figure's candidate pairs still unresolved in closed loop after `episodes_per_task` get as many again, up
    #: to this many (graftcache.rollout.sequential: two looks, each at 97.5%, 5% per pair over both)
    until_resolved: int = 8
    #: the dose family (graftcache.fit.dose) on the figure's (backbone, suite): one real-weights encoder, degraded
    #: in four steps between its plain cells (dose 0) and the zero-image policy (dose 1), on every seed
    dose_encoder: str = "efficientnet-lite0"
    doses: tuple[str, ...] = ("noise-0.25", "noise-0.5", "noise-0.75", "noise-0.9")


CLOSED_LOOP = ClosedLoopDemo()


@dataclass(frozen=True)
class ClosedLoopCells:
    """The run_ids `demo --closed-loop` rolls out: the figure's cells, on `episodes_per_task` episodes, and the
    other (backbone, suite)s' paired cells, on `paired_episodes_per_task`."""

    figure: tuple[str, ...]
    paired: tuple[str, ...]


def closed_loop_run_ids(results: pl.DataFrame, demo: ClosedLoopDemo = CLOSED_LOOP,
                        log: Callable[[str], None] = write) -> ClosedLoopCells:
    """The cells `demo --closed-loop` rolls out of `results` (see the module docstring): on the figure's
    (backbone, suite), every row with a closed-loop meaning (not shuffled-image: graftcache.fit.controls), one per
    policy; on the others, native and the top encoder's zero-image rows of `paired_seeds`. A figure's
    (backbone, suite) missing from `results` is an error: there would be no figure. Which run stands for a policy
    of several is said in `log`."""
    backbone, suite = demo.figure
    live = results.filter(pl.col("control").map_elements(lambda c: get_control(c).closed_loop, pl.Boolean))
    figure = live.filter((pl.col("backbone") == backbone) & (pl.col("suite") == suite))
    if not figure.height:
        raise GraftcacheError(f"no row of {backbone} on {suite} in the results: the closed-loop figure has no cells")
    others = live.join(figure.select("run_id"), on="run_id", how="anti")
    paired = (select_rows(others, top=1, log=log).filter(pl.col("control").is_in([NATIVE_CONTROL, ZERO_IMAGE])
                                                        & pl.col("seed").is_in(list(demo.paired_seeds)))
              if others.height else others)
    chosen = select_rows(figure, run_ids=figure["run_id"].to_list(), log=log)
    return ClosedLoopCells(figure=tuple(chosen["run_id"].to_list()), paired=tuple(paired["run_id"].to_list()))


def _dose_recipe(recipe: Recipe, demo: ClosedLoopDemo) -> Recipe:
    """The demo recipe narrowed to the dose family's cells: the figure's backbone and suite, the dose encoder, the
    demo's seeds and doses (and the plain control every fit holds, already in the results)."""
    backbone, suite = demo.figure
    backbones = tuple(b for b in recipe.backbones if b.name == backbone)
    encoders = tuple(e for e in recipe.encoders if e.name == demo.dose_encoder)
    if not backbones or not encoders:
        raise GraftcacheError(f"the demo recipe has no backbone {backbone} or no encoder {demo.dose_encoder}: the dose "
                              "family has no cells")
    return dataclasses.replace(recipe, backbones=backbones, encoders=encoders, suites=(suite,), controls=demo.doses)


def run_closed_loop_demo(recipe_path: str | Path | None = None, out: str | Path | None = None,
                         demo: ClosedLoopDemo = CLOSED_LOOP) -> ReportPaths:
    """Fit the demo's cells (resumable), roll out its episodes (resumable), and write the report with them."""
    from graftcache.executors import get_executor
    from graftcache.requests import ExecutorSettings
    from graftcache.rollout.episodes import Simulator
    from graftcache.rollout.libero import LiberoSimulator
    from graftcache.rollout.request import EXPORTS_FOLDER, RolloutRequest, default_rollouts
    from graftcache.rollout.roll_out import roll_out_started
    from graftcache.rollout.select import Selection, select
    from graftcache.rollout.sequential import Sequential, looks
    from graftcache.rollout.simulator_setup import require_simulator

    require_simulator()  # before minutes of fitting
    path = Path(recipe_path) if recipe_path else DEFAULT_RECIPE
    if not path.is_file():
        raise GraftcacheError(f"{path}: demo recipe not found (run from a checkout of graftcache, or pass --recipe)")
    t0 = time.perf_counter()
    recipe = load_recipe(path)
    results = cache_root(recipe.cache) / demo.results
    recipe = dataclasses.replace(recipe, seeds=demo.seeds, controls=demo.controls, results=str(results))
    state = run_sweep(recipe)
    run_sweep(_dose_recipe(recipe, demo))  # its caches and plain cells are the sweep's: only the doses are fitted
    table = read_for_report(results)
    cells = closed_loop_run_ids(table, demo)
    rollouts = default_rollouts(results)
    command = f"graftcache demo --closed-loop --recipe {path}"
    spawn = partial(LiberoSimulator, results, rollouts.parent / EXPORTS_FOLDER, cache=recipe.cache, runs=None,
                    max_steps=demo.max_steps)
    selections = [select(RolloutRequest(results=results, rollouts=rollouts, run_ids=run_ids, tasks=demo.tasks,
                                        episodes_per_task=episodes, max_steps=demo.max_steps,
                                        perturb_cm=demo.perturb_cm, command=command), table, write)
                  for run_ids, episodes in ((cells.figure, demo.episodes_per_task),
                                            (cells.paired, demo.paired_episodes_per_task))]
    figure = selections[0]
    sequential = Sequential(cap=demo.until_resolved)

    def expand(sel: Selection, sim: Simulator) -> Iterable[Selection]:
        """The figure's request in looks (its unresolved candidate pairs get more episodes), the paired one as it is."""
        return looks(sel, sim, seq=sequential, log=write) if sel is figure else (sel,)

    # one team for both: its workers start first, their simulators building while this process builds its own
    team = get_executor(ExecutorSettings()).rollout_team(figure.req, spawn, demo.workers, write)
    roll_out_started(selections, spawn, team, expand=expand)
    report_dir = Path(out) if out else results.parent / "report"
    commands = {"demo --closed-loop": command, **state.commands}
    paths = write_report(results, report_dir, commands=commands, rollouts=rollouts)
    write(f"closed-loop demo finished in {time.perf_counter() - t0:.0f}s")
    return paths
