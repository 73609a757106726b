"""The episodes a rollout request asks (`episodes_of`), what an episode returns (Outcome) and what a written one
reports (EpisodeReport), as plain data, and the interface between the rollout's bookkeeping
(graftcache.rollout.roll_out) and whatever runs the episodes (graftcache.rollout.libero.LiberoSimulator, or a test's
fake): a `Simulator` says what a suite is and runs a cell's episodes."""

from __future__ import annotations

from collections.abc import Iterator, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from typing import Any, Protocol

import polars as pl

from graftcache.errors import RolloutError
from graftcache.rollout.graded import Graded
from graftcache.rollout.request import RESETS, RolloutRequest
from graftcache.rollout.rollouts_file import episode_id


@dataclass(frozen=True)
class Episode:
    """One episode a request asks: episode k of a task runs from the task's init state k (mod their number) with the
    environment seeded `seed`, the start seed + k, as lerobot-eval runs its episode k with --eval.batch_size=1.
    `perturbation_m`: the target slid by up to that much per planar axis before the first step
    (graftcache.rollout.perturb, drawn from the seed); 0: the official init state as it is. `reset`: how the scene
    gets to its init state (graftcache.rollout.request.RESETS), not part of the episode's identity: either gives the
    same episode."""

    run_id: str
    suite: str
    task_index: int
    episode: int
    seed: int
    max_steps: int
    perturbation_m: float = 0.0
    reset: str = field(default=RESETS[0], compare=False)

    @property
    def id(self) -> str:
        return episode_id(asdict(self))


@dataclass(frozen=True)
class Outcome:
    """What running an Episode gave. `frames`: when the simulator records them, every frame lerobot's rollout
    rendered for the episode, (steps + 1, H, W, 3) uint8 (one after the reset, one after each step), shown at `fps`
    frames a second; None: nothing recorded. `graded`: the episode's graded progress from the simulator's state
    (graftcache.rollout.graded); `target_offset_m`: the planar (x, y) offset applied to the target, (0, 0) when
    none; `kernels`: where the policy computed (graftcache.runtime.kernels); None for any: not measured."""

    success: bool
    steps: int
    seconds: float
    init_state: int
    frames: Any = field(default=None, compare=False, repr=False)
    fps: float | None = None
    graded: Graded | None = None
    target_offset_m: tuple[float, float] | None = None
    kernels: str | None = None


@dataclass(frozen=True)
class EpisodeReport:
    """What a finished (and written) episode tells the one loop (graftcache.rollout.schedule.drive), wherever it
    ran: what its cell's summary line tallies. `video`: its path relative to the rollouts file; None: none
    recorded."""

    success: bool
    steps: int
    seconds: float
    video: str | None

    @classmethod
    def of(cls, row: Mapping[str, Any]) -> EpisodeReport:
        """The report of the episode whose rollouts row is `row` (graftcache.rollout.record.row_of)."""
        return cls(row["success"], row["steps"], row["seconds"], row["video"])


@dataclass(frozen=True)
class Suite:
    """What the simulator says of a suite: how many tasks it has and lerobot's episode length for it."""

    n_tasks: int
    max_steps: int


class Simulator(Protocol):
    """Runs a results row's cell in closed loop. `suite` is asked before anything runs (for the request's episodes,
    `episodes_of`); `run` gets the cell's row and its missing episodes and yields one Outcome per episode, in order,
    as each finishes (the rollout writes each row as it comes, so a killed run keeps the episodes it finished), with
    its frames when the simulator was built to record them (the rollout writes them as the episode's video)."""

    def suite(self, name: str) -> Suite: ...

    def run(self, row: Mapping[str, Any], episodes: Sequence[Episode]) -> Iterator[Outcome]: ...


def episodes_of(rows: pl.DataFrame, req: RolloutRequest, simulator: Simulator) -> list[Episode]:
    """Every episode `req` asks of its selected `rows`, cell by cell: per row, its suite's tasks x
    episodes_per_task."""
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


def where(episode: Episode) -> str:
    """The episode in the words of a one-line error or log line."""
    return (f"run {episode.run_id}, {episode.suite} task {episode.task_index} episode {episode.episode} "
            f"(seed {episode.seed})")
