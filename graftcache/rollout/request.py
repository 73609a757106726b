"""What `graftcache rollout` is asked (RolloutRequest), refused in one line past what an episode's seed, the request's
episodes and a perturbation's resolution can hold, and where its files go by default."""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

from graftcache.errors import RolloutError
from graftcache.requests import DEVICE_HELP

ROLLOUTS_FILE = "rollouts.parquet"  # the default: beside the results file
EXPORTS_FOLDER = "exports"          # beside the rollouts file: one export folder per run_id
MAX_SEED = 2**32 - 1                # numpy's and gymnasium's seeds are unsigned 32-bit integers
#: LIBERO has 50 official init states per task (episode k starts from state k mod 50): 1,000 episodes a task is
#: 20 passes over them, past any study's need, and keeps a request that hashes every episode small
MAX_EPISODES_PER_TASK = 1000
#: --perturb-cm's largest offset, a bound on what is asked rather than a measured limit: the sample slides its targets
#: up to 3 cm, and an offset that puts the target on a neighbour is refused by the settling check anyway
MAX_PERTURB_CM = 10.0
#: --perturb-cm's resolution: a tenth of a millimetre, far below what settling and the simulator's contacts resolve.
#: A finer value is refused rather than rounded: each value is another episode key, so 1e-300 would make "perturbed"
#: episodes of the official scenes, and 3.000001 episodes apart from 3's of the same scenes.
PERTURB_RESOLUTION_CM = 0.01
#: The devices an episode's policy may run on (graftcache.requests.DEVICE_HELP); runtime.resolve_device then says
#: whether this machine has it
DEVICE = re.compile(r"cpu|cuda(:\d+)?")
#: How an episode's scene is reset to its init state: "soft", lerobot's reset keeping the MjSim with the renders
#: nobody sees skipped (graftcache.rollout.seam), or "hard", lerobot-eval's own (a new MjSim and render context each
#: episode). Their episodes are the same, state for state and image for image (tests/rollout/test_soft_reset.py), so
#: rows do not record which ran, as they do not record how many workers ran them.
RESETS = ("soft", "hard")


@dataclass(frozen=True)
class RolloutRequest:
    """What `graftcache rollout` was asked: which rows (run_ids, else the `top` encoders by `score` plus controls,
    within `suites`), which tasks (None: all of the suite's), how many episodes each, the step limit (None:
    lerobot's episode length of the suite), the start seed shared by every cell (episodes are paired), and the
    target's perturbation (up to `perturb_cm` per planar axis, drawn from each episode's seed; 0: the official init
    states), how each scene is reset (RESETS) and where each episode's policy runs (`device`: its rows record the
    kernels that computed it)."""

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
    device: str = "cpu"
    command: str = ""

    def __post_init__(self) -> None:
        """Refuse, in one line, counts past what an episode's seed and the request's episodes can hold: episode k is
        seeded seed + k, which numpy's and the simulator's seeding take as an unsigned 32-bit integer."""
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
        if not DEVICE.fullmatch(self.device):
            raise RolloutError(f"--device {self.device}: must be {DEVICE_HELP}")


def default_rollouts(results_path: str | Path) -> Path:
    return Path(results_path).absolute().parent / ROLLOUTS_FILE
