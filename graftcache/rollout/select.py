"""Which results rows `graftcache rollout` runs: the top encoders of each (backbone, suite) by the report's own
ranking plus their controls, or exactly the run_ids asked for; each checked to be runnable in the simulator before
anything is exported or started.

The ranking is the report's (graftcache.analysis.rankings of the table graftcache.analysis.scored puts the chosen
score in): the K encoders with the lowest mean score over seeds, ties broken by name as the report lists them.
Every seed's row of those encoders is rolled out (agreement is computed over run_ids, graftcache.analysis.
closed_loop), with each one's zero-image rows (its own control: the same fit with no visual information) and the
backbone's native rows (its own tower). shuffled-image rows are never picked: they feed other frames' features, which
no live camera can (graftcache.fit.controls.Control.closed_loop).

A policy is rolled out once (`one_per_policy`): rows of one policy_id (the native tower's of every seed; zero-image
rows of encoders whose caches hold the same frames) are one function of the simulator's observations, whose
episodes would only be counted again.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import polars as pl

from graftcache.analysis import NATIVE_CONTROL, PLAIN, ZERO_IMAGE, rankings, scored
from graftcache.cameras import parse_camera_map
from graftcache.datasets.suites import suite_tasks
from graftcache.errors import RolloutError
from graftcache.fit.controls import get_control
from graftcache.results import conform, read_for_report
from graftcache.rollout.request import RolloutRequest

#: Controls rolled out beside the top encoders' plain grafts (CONTROLS_OF_ENCODER: the selected encoders' own rows)
CONTROLS_OF_ENCODER = (ZERO_IMAGE,)
CONTROLS_OF_BACKBONE = (NATIVE_CONTROL,)
#: The cameras lerobot's LIBERO env feeds (lerobot/envs/libero.py: agentview_image -> image, robot0_eye_in_hand_image
#: -> image2): a cell whose cache cameras are others cannot be fed by it
SIMULATOR_CAMERAS = {"image": "agentview", "image2": "wrist (eye in hand)"}
#: The LIBERO suites lerobot's env builds (its TASK_SUITE_MAX_STEPS), as plain data
SIMULATOR_SUITES = ("libero_spatial", "libero_object", "libero_goal", "libero_10", "libero_90")
ORDER = ("backbone", "suite", "control", "encoder", "seed")


@dataclass(frozen=True, eq=False)
class Selection:
    """A request with what it selected, handed on so that nothing after it reads the results file or selects again:
    `rows` (select_rows of `results`, in ORDER), `results` (the results table they were selected from, which a
    sequential rollout's looks join their rollouts to, graftcache.rollout.sequential) and `req`, whose run_ids are
    `rows`' (chosen once, and said once)."""

    req: RolloutRequest
    rows: pl.DataFrame
    results: pl.DataFrame

    def narrowed(self, rows: pl.DataFrame, **fields: object) -> Selection:
        """This selection with `rows`, some of its own, and the request's `fields` replaced: a later request of the
        same command (a sequential rollout's next look) that selects no row again."""
        req = dataclasses.replace(self.req, run_ids=tuple(rows["run_id"].to_list()), **fields)
        return Selection(req, rows, self.results)


def select(req: RolloutRequest, results: pl.DataFrame | None = None,
           log: Callable[[str], None] = print) -> Selection:
    """The rows `req` asks of `results` (None: its results file, read here), each checked runnable (select_rows)."""
    table = read_for_report(req.results) if results is None else results
    rows = select_rows(table, run_ids=req.run_ids, top=req.top, suites=req.suites, score=req.score, log=log)
    return Selection(dataclasses.replace(req, run_ids=tuple(rows["run_id"].to_list())), rows, table)


def select_rows(results: pl.DataFrame, *, run_ids: Sequence[str] | None = None, top: int = 3,
                suites: Sequence[str] | None = None, score: str = "mse",
                log: Callable[[str], None] = print) -> pl.DataFrame:
    """The rows to roll out, in (backbone, suite, control, encoder, seed) order: exactly `run_ids` (each must be a
    row, of a suite in `suites` when given), else per (backbone, suite) among `suites` the `top` best encoders'
    plain, zero-image rows and the native rows; of each policy, one row (`one_per_policy`, said in `log`). Each is
    checked by `check_row`; a name of `suites` that is no LIBERO suite is refused as such (it selected no row before,
    and was refused as a ranking of nothing)."""
    odd = [s for s in suites or () if s not in SIMULATOR_SUITES]
    if odd:
        raise RolloutError(f"--suites {odd[0]}: not a LIBERO suite ({', '.join(SIMULATOR_SUITES)})")
    if run_ids is not None:
        chosen = _exact(results, run_ids, suites)
    else:
        table = results if suites is None else results.filter(pl.col("suite").is_in(list(suites)))
        chosen = _best(table, top, score)
        if not chosen.height:
            where = f" of suite(s) {', '.join(suites)}" if suites else ""
            raise RolloutError(f"no plain-graft row with a score{where} to rank: nothing to roll out")
    for row in chosen.iter_rows(named=True):
        check_row(row)
    return one_per_policy(chosen, log).sort(ORDER)


def one_per_policy(chosen: pl.DataFrame, log: Callable[[str], None]) -> pl.DataFrame:
    """`chosen` with one row per policy (policy_id; a table without one: each run its own): the lowest seed's, then
    the first encoder's by name, then the lowest run_id; each policy that had several rows is said in one line,
    naming the run rolled out for them all."""
    keyed = chosen.with_columns(pl.coalesce("policy_id", "run_id").alias("_policy")) if "policy_id" in chosen.columns \
        else chosen.with_columns(pl.col("run_id").alias("_policy"))
    ordered = keyed.sort("seed", "encoder", "run_id")
    kept = ordered.unique("_policy", keep="first", maintain_order=True)
    for policy, group in ordered.group_by("_policy", maintain_order=True):
        if group.height > 1:
            first, *others = group.iter_rows(named=True)
            log(f"runs {', '.join(r['run_id'] for r in others)} are the policy of run {first['run_id']} "
                f"({first['backbone']}/{first['encoder']}/{first['suite']} control {first['control']} seed "
                f"{first['seed']}, policy {policy[0]}): rolled out once, as run {first['run_id']}")
    return chosen.join(kept.select("run_id"), on="run_id", how="semi")


def _exact(results: pl.DataFrame, run_ids: Sequence[str], suites: Sequence[str] | None) -> pl.DataFrame:
    known = set(results["run_id"].to_list())
    unknown = [r for r in run_ids if r not in known]
    if unknown:
        raise RolloutError(f"run {unknown[0]}: no such row in the results file")
    chosen = results.filter(pl.col("run_id").is_in(list(run_ids)))
    if suites is not None:
        for row in chosen.iter_rows(named=True):
            if row["suite"] not in suites:
                raise RolloutError(f"run {row['run_id']}: fit on {row['suite']}, not among --suites {','.join(suites)}")
    return chosen


def _best(table: pl.DataFrame, top: int, score: str) -> pl.DataFrame:
    """The top encoders' plain and zero-image rows and the native rows, per (backbone, suite) of `table`."""
    ranked = rankings(scored(conform(table), score)).drop_nulls("rank")
    best = ranked.group_by("backbone", "suite", maintain_order=True).head(top).select("backbone", "suite", "encoder")
    of_encoder = table.filter(pl.col("control").is_in([PLAIN, *CONTROLS_OF_ENCODER])).join(
        best, on=["backbone", "suite", "encoder"], how="semi")
    of_backbone = table.filter(pl.col("control").is_in(list(CONTROLS_OF_BACKBONE))).join(
        best.select("backbone", "suite").unique(), on=["backbone", "suite"], how="semi")
    return pl.concat([of_encoder, of_backbone])


def check_tasks(rows: pl.DataFrame, tasks: Sequence[int] | None) -> None:
    """Refuse, in one line naming the run, a task its suite lacks, counted from the LIBERO benchmark's task lists
    (graftcache.datasets.suites), so that it is refused before the simulator is imported
    (graftcache.rollout.episodes.episodes_of checks again)."""
    counts = {suite: len(names) for suite, names in suite_tasks().items()}
    for row in rows.iter_rows(named=True):
        beyond = [t for t in tasks or () if t >= counts[row["suite"]]]
        if beyond:
            raise RolloutError(f"run {row['run_id']}: suite {row['suite']} has tasks 0-{counts[row['suite']] - 1}, "
                               f"not task {beyond[0]}")


def check_row(row: dict) -> None:
    """Refuse, in one line naming the run, a row the simulator cannot run: a control without a closed-loop meaning,
    a suite lerobot's LIBERO env does not build, cache cameras it does not feed."""
    where = f"run {row['run_id']} ({row['backbone']}/{row['encoder']}/{row['suite']}, control {row['control']})"
    if not get_control(row["control"]).closed_loop:
        raise RolloutError(f"{where}: control {row['control']} has no closed-loop meaning (it feeds features of other "
                           "frames); roll out another control")
    if row["suite"] not in SIMULATOR_SUITES:
        raise RolloutError(f"{where}: suite {row['suite']} is not one the LIBERO simulator builds "
                           f"({', '.join(SIMULATOR_SUITES)})")
    fed = parse_camera_map(row["camera_map"]) if row["camera_map"] else {}
    foreign = sorted(c for c in fed.values() if c not in SIMULATOR_CAMERAS)
    if not fed or foreign:
        simulator = ", ".join(f"{k} ({v})" for k, v in SIMULATOR_CAMERAS.items())
        raise RolloutError(f"{where}: its cache cameras {', '.join(foreign) or '(none recorded)'} are not cameras "
                           f"the LIBERO simulator feeds ({simulator}); extract and fit it from a dataset whose cameras "
                           "are named image/image2")
