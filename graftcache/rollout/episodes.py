"""What a rollout plans and what an episode returns, as plain data, and the interface between the rollout's
bookkeeping (graftcache.rollout.run) and whatever runs the episodes (graftcache.rollout.libero.LiberoSimulator, or a
test's fake): a `Simulator` says what a suite is and runs a cell's episodes."""

from __future__ import annotations

from collections.abc import Iterator, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from typing import Any, Protocol

from graftcache.rollout.graded import Graded
from graftcache.rollout.table import episode_id

#: How an episode's scene is reset to its init state: "soft", lerobot's reset keeping the MjSim with the renders
#: nobody sees skipped (graftcache.rollout.seam), or "hard", lerobot-eval's own (a new MjSim and render context each
#: episode). Their episodes are the same, state for state and image for image (tests/rollout/test_soft_reset.py), so
#: rows do not record which ran, as they do not record how many workers ran them.
RESETS = ("soft", "hard")


@dataclass(frozen=True)
class Episode:
    """One planned episode: episode k of a task runs from the task's init state k (mod their number) with the
    environment seeded `seed`, the start seed + k, as lerobot-eval runs its episode k with --eval.batch_size=1.
    `perturbation_m`: the target slid by up to that much per planar axis before the first step
    (graftcache.rollout.perturb, drawn from the seed); 0: the official init state as it is. `reset`: how the scene
    gets to its init state (RESETS), not part of the episode's identity: either gives the same episode."""

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
    none; None for either: not measured."""

    success: bool
    steps: int
    seconds: float
    init_state: int
    frames: Any = field(default=None, compare=False, repr=False)
    fps: float | None = None
    graded: Graded | None = None
    target_offset_m: tuple[float, float] | None = None


@dataclass(frozen=True)
class Suite:
    """What the simulator says of a suite: how many tasks it has and lerobot's episode length for it."""

    n_tasks: int
    max_steps: int


class Simulator(Protocol):
    """Runs a results row's cell in closed loop. `suite` is asked before anything runs (to plan); `run` gets the
    cell's row and its missing episodes and yields one Outcome per episode, in order, as each finishes (the rollout
    writes each row as it comes, so a killed run keeps the episodes it finished), with its frames when the simulator
    was built to record them (the rollout writes them as the episode's video)."""

    def suite(self, name: str) -> Suite: ...

    def run(self, row: Mapping[str, Any], episodes: Sequence[Episode]) -> Iterator[Outcome]: ...
