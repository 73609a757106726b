"""`graftcache rollout`: a selection's episodes (graftcache.rollout.select.Selection, the request with its rows),
those already in the rollouts file skipped, the rest handed to a team (graftcache.rollout.teams.Team) through the one
loop (graftcache.rollout.schedule.drive), which runs them cell by cell under the cell's claim; each episode is written
one row as it finishes (graftcache.rollout.record).

Resuming is by episode: a rerun of the same command asks the same episodes (graftcache.rollout.episodes.Episode,
identified by graftcache.rollout.rollouts_file.EPISODE_KEY), finds them in the file and runs none, saying so; a run
killed mid-way (kill -9 included) has written every episode it finished, and its rerun runs the others. Two processes
sharing a rollouts file take each cell under its claim (graftcache.results.claims.cell_claim, beside the file), and
look again at what the file holds once they have it, so no episode is run twice.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence

import polars as pl

from graftcache.errors import RolloutError
from graftcache.progress import progress
from graftcache.progress import write as progress_write
from graftcache.results.claims import drop_claims_folder
from graftcache.rollout import rollouts_file
from graftcache.rollout.episodes import Episode, Simulator, episodes_of
from graftcache.rollout.schedule import Scheduler, drive
from graftcache.rollout.select import Selection
from graftcache.rollout.teams import InProcess, Team


def roll_out(sel: Selection, sim: Simulator, log: Callable[[str], None] = progress_write, *,
             team: Team | None = None) -> pl.DataFrame:
    """Run the missing episodes of the selection's request and return the rollouts file's rows of its episodes: in
    this process, by `sim` (the team of one, InProcess), or by `team` (each of its workers with a simulator of its
    own), `sim` then only saying what its suites are (graftcache.rollout.episodes.episodes_of)."""
    req = sel.req
    episodes = episodes_of(sel.rows, req, sim)
    written = rollouts_file.read(req.rollouts)
    done = set(written["episode_id"].to_list())
    missing = [e for e in episodes if e.id not in done]
    cells = sel.rows.height
    if not missing:
        log(f"all {len(episodes)} episodes of {cells} cell(s) are already in {req.rollouts}: nothing to run")
        return _of(written, episodes)
    if len(missing) < len(episodes):
        log(f"{len(episodes) - len(missing)} of {len(episodes)} episodes already in {req.rollouts}; running the "
            f"other {len(missing)}")
    slid = f", targets slid up to {req.perturb_cm:g} cm" if req.perturb_cm else ""
    log(f"rolling out {cells} cell(s), {len(missing)} episode(s) into {req.rollouts}{slid}")
    by_run = {r["run_id"]: r for r in sel.rows.iter_rows(named=True)}
    runner = team or InProcess(sim, req)
    try:
        with progress(total=len(missing), desc="rollout", unit="episode") as bar:
            runner.begin(req, len(missing), log)
            drive(Scheduler(req.rollouts, by_run, missing, bar, log), runner)
    finally:  # stopped or failed too: no empty claims folder is left beside the file
        drop_claims_folder(req.rollouts)
    return _of(rollouts_file.read(req.rollouts), episodes)


def roll_out_started(selections: Sequence[Selection], spawn: Callable[[], Simulator], team: Team | None,
                     log: Callable[[str], None] = progress_write, *,
                     expand: Callable[[Selection, Simulator], Iterable[Selection]] | None = None) -> pl.DataFrame:
    """`roll_out` of each selection in turn, with one simulator built by `spawn` here, after `team` was started
    (None: none), so that the team's workers build theirs meanwhile; the simulator and the team are closed when the
    last ends, however it ends. Returns the rows of every request's episodes, in order. `expand`: each selection
    becomes the selections it yields, each asked for once the one before was rolled out (a sequential rollout's
    looks, graftcache.rollout.sequential.looks, decide each from what the last wrote).

    Why several requests: requests that differ in what one request holds for all its cells (the closed-loop demo's
    figure and paired cells differ in episodes per task) share the team's start-up, a simulator's imports and build
    in each worker. They must share the rollouts file and command, which the team's workers were started with."""
    try:
        if len({(s.req.rollouts, s.req.command) for s in selections}) > 1:
            raise RolloutError("requests rolled out by one team must share their rollouts file and command: "
                               + "; ".join(f"{s.req.rollouts} ({s.req.command!r})" for s in selections))
        sim = spawn()  # with a team, it only says what its suites are
        try:
            each = (s for sel in selections for s in expand(sel, sim)) if expand is not None else selections
            rows = pl.concat([roll_out(sel, sim, log, team=team) for sel in each])
            return rows.unique("episode_id", keep="first", maintain_order=True)
        finally:
            close = getattr(sim, "close", None)
            if close is not None:
                close()
    finally:
        if team is not None:
            team.close()


def _of(rows: pl.DataFrame, episodes: Sequence[Episode]) -> pl.DataFrame:
    """The rollouts rows of `episodes`."""
    return rows.filter(pl.col("episode_id").is_in([e.id for e in episodes]))
