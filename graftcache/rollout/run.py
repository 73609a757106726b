"""`graftcache rollout`: the selected cells' episodes planned, those already in the rollouts file skipped, the rest
run cell by cell under the cell's claim and written one row per episode as each finishes.

Resuming is by episode: a rerun of the same command plans the same episodes (graftcache.rollout.episodes.Episode,
identified by graftcache.rollout.table.EPISODE_KEY), finds them in the file and runs none, saying so; a run killed
mid-way (kill -9 included) has written every episode it finished, and its rerun runs the others. Two processes
sharing a rollouts file take each cell under its claim (graftcache.results.claims.cell_claim, beside the file), and look
again at what the file holds once they have it, so no episode is run twice.

Videos (a simulator built to record frames): each episode's video is written whole (a temporary name, synced, then
renamed) under videos/ beside the rollouts file before its row is appended, and the row names it relative to the
file; so a row never names a partial video, and an episode rerun because its row is missing overwrites its video.
"""

from __future__ import annotations

import importlib.metadata
import os
import socket
import uuid
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any, Protocol

import polars as pl

import graftcache
from graftcache import results
from graftcache.errors import RolloutError
from graftcache.progress import progress
from graftcache.progress import write as progress_write
from graftcache.results.claims import drop_claims_folder
from graftcache.results.writing import fsync
from graftcache.rollout import table
from graftcache.rollout.episodes import RESETS, Episode, Outcome, Simulator
from graftcache.rollout.graded import Graded
from graftcache.rollout.schedule import VIDEOS_FOLDER, EpisodeReport, Job, Scheduler, drive, pause, where
from graftcache.rollout.select import select_rows

ROLLOUTS_FILE = "rollouts.parquet"  # the default: beside the results file
EXPORTS_FOLDER = "exports"          # beside the rollouts file: one export folder per run_id
GRADED_FIELDS = tuple(f.name for f in fields(Graded))  # the row's columns of an Outcome's `graded`
MAX_SEED = 2**32 - 1                # numpy's and gymnasium's seeds are unsigned 32-bit integers
#: LIBERO has 50 official init states per task (episode k starts from state k mod 50): 1,000 episodes a task is
#: 20 passes over them, past any study's need, and keeps a plan that hashes every episode small
MAX_EPISODES_PER_TASK = 1000
#: --perturb-cm's largest offset, a bound on what is asked rather than a measured limit: the sample slides its targets
#: up to 3 cm, and an offset that puts the target on a neighbour is refused by the settling check anyway
MAX_PERTURB_CM = 10.0
#: --perturb-cm's resolution: a tenth of a millimetre, far below what settling and the simulator's contacts resolve.
#: A finer value is refused rather than rounded: each value is another episode key, so 1e-300 would make "perturbed"
#: episodes of the official scenes, and 3.000001 episodes apart from 3's of the same scenes.
PERTURB_RESOLUTION_CM = 0.01


@dataclass(frozen=True)
class RolloutRequest:
    """What `graftcache rollout` was asked: which rows (run_ids, else the `top` encoders by `score` plus controls,
    within `suites`), which tasks (None: all of the suite's), how many episodes each, the step limit (None:
    lerobot's episode length of the suite), the start seed shared by every cell (episodes are paired), and the
    target's perturbation (up to `perturb_cm` per planar axis, drawn from each episode's seed; 0: the official init
    states) and how each scene is reset (graftcache.rollout.episodes.RESETS)."""

    results: Path
    rollouts: Path
    run_ids: tuple[str, ...] | None = None
    top: int = 3
    suites: tuple[str, ...] | None = None
    score: str = "mse"
    tasks: tuple[int, ...] | None = None
    episodes_per_task: int = 1
    max_steps: int | None = None
    seed: int = 1000
    perturb_cm: float = 0.0
    reset: str = RESETS[0]
    command: str = ""

    def __post_init__(self) -> None:
        """Refuse, in one line, counts past what an episode's seed and the plan can hold: episode k is seeded
        seed + k, which numpy's and the simulator's seeding take as an unsigned 32-bit integer."""
        if not 1 <= self.episodes_per_task <= MAX_EPISODES_PER_TASK:
            raise RolloutError(f"--episodes-per-task {self.episodes_per_task}: must be 1 to {MAX_EPISODES_PER_TASK}")
        last = self.seed + self.episodes_per_task - 1
        if self.seed < 0 or last > MAX_SEED:
            raise RolloutError(f"--seed {self.seed}: episodes are seeded {self.seed} to {last}, which must lie in 0 to "
                               f"{MAX_SEED} (an unsigned 32-bit seed)")
        if not 0 <= self.perturb_cm <= MAX_PERTURB_CM:  # NaN fails it too
            raise RolloutError(f"--perturb-cm {self.perturb_cm}: must be 0 to {MAX_PERTURB_CM:g} (cm)")
        steps = self.perturb_cm / PERTURB_RESOLUTION_CM
        if abs(steps - round(steps)) > 1e-6 or (steps and not round(steps)):
            raise RolloutError(f"--perturb-cm {self.perturb_cm:g}: finer than its resolution, "
                               f"{PERTURB_RESOLUTION_CM:g} cm (0: none)")
        if self.reset not in RESETS:
            raise RolloutError(f"--reset {self.reset}: must be one of {', '.join(RESETS)}")


def default_rollouts(results_path: str | Path) -> Path:
    return Path(results_path).absolute().parent / ROLLOUTS_FILE


def plan(rows: pl.DataFrame, req: RolloutRequest, simulator: Simulator) -> list[Episode]:
    """Every episode of the request, cell by cell: per row, its suite's tasks x episodes_per_task."""
    episodes = []
    for row in rows.iter_rows(named=True):
        suite = simulator.suite(row["suite"])
        tasks = req.tasks if req.tasks is not None else tuple(range(suite.n_tasks))
        beyond = [t for t in tasks if t >= suite.n_tasks]
        if beyond:
            raise RolloutError(f"run {row['run_id']}: suite {row['suite']} has tasks 0-{suite.n_tasks - 1}, not "
                               f"task {beyond[0]}")
        episodes += [Episode(row["run_id"], row["suite"], t, k, req.seed + k, suite.max_steps, req.perturb_cm / 100,
                             req.reset) for t in tasks for k in range(req.episodes_per_task)]
    return episodes


def video_of(episode: Episode) -> str:
    """The episode's video, relative to the rollouts file: named by every field of its episode_id, so episodes of
    other seeds, step limits or perturbations never share one."""
    perturbed = f"_perturb{episode.perturbation_m:g}m" if episode.perturbation_m else ""
    return (f"{VIDEOS_FOLDER}/{episode.run_id}/{episode.suite}_task{episode.task_index}_ep{episode.episode}"
            f"_seed{episode.seed}_max{episode.max_steps}{perturbed}.mp4")


def write_video(path: Path, outcome: Outcome) -> None:
    """The outcome's frames as lerobot-eval writes its videos (lerobot.utils.io_utils.write_video: H.264, yuv420p,
    at the env's render fps), to a temporary name beside `path`, synced and renamed over it: `path` is whole or
    absent (an older one is replaced). The temporary file never outlives the call (kill -9 aside)."""
    from lerobot.utils.io_utils import write_video as lerobot_write_video

    path.parent.mkdir(parents=True, exist_ok=True)
    # ends in .mp4: the container is chosen by the name
    tmp = path.with_name(f".{path.stem}.{socket.gethostname()}.{os.getpid()}.{uuid.uuid4().hex[:8]}.tmp.mp4")
    try:
        lerobot_write_video(tmp, list(outcome.frames), outcome.fps)
        fsync(tmp)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    try:  # the rename survives a crash once its folder is synced, as the row's append does for the rollouts file
        fsync(path.parent)
    except OSError:
        pass


def row_of(episode: Episode, outcome: Outcome, command: str, video: str | None = None) -> dict[str, Any]:
    """The rollouts row of a finished episode (graftcache.rollout.table.SCHEMA); `video`: its path, relative to the
    rollouts file. What the simulator did not measure (an Outcome without `graded` or `target_offset_m`) is null."""
    graded = asdict(outcome.graded) if outcome.graded is not None else dict.fromkeys(GRADED_FIELDS)
    offset_x, offset_y = outcome.target_offset_m if outcome.target_offset_m is not None else (None, None)
    return {"episode_id": episode.id, "format_version": table.FORMAT_VERSION, "run_id": episode.run_id,
            "suite": episode.suite, "task_index": episode.task_index, "episode": episode.episode,
            "seed": episode.seed, "init_state": outcome.init_state, "max_steps": episode.max_steps,
            "success": outcome.success, "steps": outcome.steps, "seconds": outcome.seconds, "video": video,
            "perturbation_m": episode.perturbation_m, "target_offset_x_m": offset_x, "target_offset_y_m": offset_y,
            **graded, "lerobot_version": importlib.metadata.version("lerobot"),
            "graftcache_version": graftcache.__version__, "command": command}


def with_video(rollouts: Path, command: str, episode: Episode, outcome: Outcome) -> dict[str, Any]:
    """A finished episode's row, its video (when it has frames) written first: the row, which names it, is for the
    caller to append (a Ray actor's row goes back to the driver, graftcache.executors.ray_rollout)."""
    video = None
    if outcome.frames is not None:
        video = video_of(episode)
        write_video(rollouts.parent / video, outcome)
    return row_of(episode, outcome, command, video)


def record(rollouts: Path, command: str, episode: Episode, outcome: Outcome) -> EpisodeReport:
    """Write a finished episode, its video (when it has frames) before its row, which names it, and report it."""
    row = with_video(rollouts, command, episode, outcome)
    table.append(rollouts, [row])
    return EpisodeReport.of(row)


def run_one(sim: Simulator, row: Mapping[str, Any], episode: Episode, rollouts: Path, command: str) -> EpisodeReport:
    """Run one episode on `sim` and `record` it as the simulator yields it, before its generator is resumed to its
    end: an error the simulator raises after its episode leaves the episode written."""
    reports = [record(rollouts, command, episode, outcome) for outcome in sim.run(row, [episode])]
    if len(reports) != 1:
        raise RolloutError(f"{where(episode)}: the simulator gave {len(reports)} outcomes for one episode")
    return reports[0]


class Team(Protocol):
    """Runs a rollout's missing episodes, each worker with a simulator of its own: spawned processes on this
    machine (graftcache.rollout.workers.Workers, `--workers N`) or Ray actors (graftcache.executors.ray_rollout.Actors,
    `--executor ray`), as an executor starts them (graftcache.executors.Executor.rollout_team), else this process's
    team of one (InProcess), and each of them the transport of the one loop (graftcache.rollout.schedule.drive).
    A team starts when built, so its simulators build while this
    process plans; it holds the claims of the cells in flight and gets every episode written. It serves requests
    one after another until closed (graftcache.rollout.run.roll_out_started), so a command of several requests
    pays for one start-up."""

    def run(self, req: RolloutRequest, rows: Mapping[str, Mapping[str, Any]], missing: Sequence[Episode], bar: Any,
            log: Callable[[str], None]) -> None:
        """Run `missing`, episodes of the cells `rows` holds by run_id, through graftcache.rollout.schedule.drive
        (the team its transport); `bar` advances by one per episode written or found written by another rollout.
        Workers beyond the number of episodes are ended at once (the team is smaller for the requests that
        follow)."""

    def close(self) -> None:
        """Every worker stopped; nothing of the team outlives it."""


@dataclass
class _Here:
    """The team of one's worker (graftcache.rollout.schedule.Worker)."""

    running: Episode | None = None
    last: str | None = None


class InProcess:
    """The team of one (`roll_out` without a team): this process's simulator runs each episode as it is sent, so
    episodes go through the loop the other teams' do (graftcache.rollout.schedule.drive). An error of the simulator
    is raised as it is."""

    def __init__(self, sim: Simulator, req: RolloutRequest) -> None:
        self.sim, self.rollouts, self.command = sim, req.rollouts, req.command
        self.workers = (_Here(),)
        self.reports: list[tuple[_Here, EpisodeReport]] = []

    def run(self, req: RolloutRequest, rows: Mapping[str, Mapping[str, Any]], missing: Sequence[Episode], bar: Any,
            log: Callable[[str], None]) -> None:
        drive(Scheduler(req.rollouts, rows, missing, bar, log), self)

    def send(self, worker: _Here, job: Job) -> None:
        row, episode = job
        self.reports.append((worker, run_one(self.sim, row, episode, self.rollouts, self.command)))

    def receive(self, timeout: float | None) -> list[tuple[_Here, EpisodeReport]]:
        if not self.reports:  # only cells another rollout holds are left
            pause(timeout)
        reports, self.reports = self.reports, []
        return reports

    def stop(self) -> None:
        """Nothing runs once the loop has stopped: each episode ran within `send`."""

    def close(self) -> None:
        """Nothing to stop: the simulator is its caller's."""


def roll_out(req: RolloutRequest, sim: Simulator, log: Callable[[str], None] = progress_write, *,
             team: Team | None = None) -> pl.DataFrame:
    """Run the request's missing episodes and return the rollouts file's rows of the request's episodes: in this
    process, by `sim` (the team of one, InProcess), or by `team` (each of its workers with a simulator of its own),
    `sim` only planning."""
    rows = select_rows(results.read_for_report(req.results), run_ids=req.run_ids, top=req.top, suites=req.suites,
                       score=req.score, log=log)
    episodes = plan(rows, req, sim)
    done = set(table.read(req.rollouts)["episode_id"].to_list())
    missing = [e for e in episodes if e.id not in done]
    cells = rows.height
    if not missing:
        log(f"all {len(episodes)} episodes of {cells} cell(s) are already in {req.rollouts}: nothing to run")
        return _of(req, episodes)
    if len(missing) < len(episodes):
        log(f"{len(episodes) - len(missing)} of {len(episodes)} episodes already in {req.rollouts}; running the "
            f"other {len(missing)}")
    slid = f", targets slid up to {req.perturb_cm:g} cm" if req.perturb_cm else ""
    log(f"rolling out {cells} cell(s), {len(missing)} episode(s) into {req.rollouts}{slid}")
    by_run = {r["run_id"]: r for r in rows.iter_rows(named=True)}
    try:
        with progress(total=len(missing), desc="rollout", unit="episode") as bar:
            (team or InProcess(sim, req)).run(req, by_run, missing, bar, log)
    finally:  # stopped or failed too: no empty claims folder is left beside the file
        drop_claims_folder(req.rollouts)
    return _of(req, episodes)


def roll_out_started(requests: Sequence[RolloutRequest], spawn: Callable[[], Simulator], team: Team | None,
                     log: Callable[[str], None] = progress_write, *,
                     expand: Callable[[RolloutRequest, Simulator], Iterable[RolloutRequest]] | None = None,
                     ) -> pl.DataFrame:
    """`roll_out` of each request in turn, with one simulator built by `spawn` here, after `team` was started (None:
    none), so that the team's workers build theirs meanwhile; the simulator and the team are closed when the last
    ends, however it ends. Returns the rows of every request's episodes, in order. `expand`: each request becomes
    the requests it yields, each asked for once the one before was rolled out (a sequential rollout's looks,
    graftcache.rollout.sequential.looks, decide each from what the last wrote).

    Why several requests: requests that differ in what one request holds for all its cells (the closed-loop demo's
    figure and paired cells differ in episodes per task) share the team's start-up, a simulator's imports and build
    in each worker. They must share the rollouts file and command, which the team's workers were started with."""
    try:
        if len({(r.rollouts, r.command) for r in requests}) > 1:
            raise RolloutError("requests rolled out by one team must share their rollouts file and command: "
                               + "; ".join(f"{r.rollouts} ({r.command!r})" for r in requests))
        sim = spawn()  # with a team, it only plans
        try:
            each = (r for req in requests for r in expand(req, sim)) if expand is not None else requests
            rows = pl.concat([roll_out(req, sim, log, team=team) for req in each])
            return rows.unique("episode_id", keep="first", maintain_order=True)
        finally:
            close = getattr(sim, "close", None)
            if close is not None:
                close()
    finally:
        if team is not None:
            team.close()


def _of(req: RolloutRequest, episodes: Sequence[Episode]) -> pl.DataFrame:
    ids = [e.id for e in episodes]
    return table.read(req.rollouts).filter(pl.col("episode_id").is_in(ids))
