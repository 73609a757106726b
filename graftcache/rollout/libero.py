"""The LIBERO simulator through lerobot's own evaluation code, in this process: each cell is exported
(graftcache.export), loaded as lerobot-eval loads a policy (make_policy, make_pre_post_processors with the overrides
lerobot-eval applies, the env's own processors), and each episode is one call of lerobot-eval's `rollout` on a
one-env vector env of lerobot's LIBERO config at the datasets' 256x256 resolution, scored as `eval_policy` scores
it (success: any step's check_success up to the first done; steps: up to it). With `videos`, each episode's frames
are those lerobot-eval's render callback takes (the env's render(): agentview as lerobot shows it, after the reset and
after every step), returned with the env's render_fps for the rollout to write as lerobot-eval writes its videos.

What differs from a `lerobot-eval` process, and why: the env of a (suite, task) is built once and serves every cell
(one process serves many cells); so that episode k still starts from init state k whatever ran before, the env's
init-state counter is set to k before its reset (lerobot-eval gets there by counting its resets from 0), and the
global RNGs are seeded from the episode's seed before it (lerobot-eval seeds them once per process), so that an
episode run again after a kill is the same episode. An episode's video holds every frame its rollout rendered
(steps + 1: after the reset and after each step); lerobot-eval's keeps the first `steps` (frames[: done_index + 1]),
dropping the one after the last step, so a graftcache video ends on the state its success was scored on. An
episode's reset is by default soft (graftcache.rollout.seam: the simulator kept, the renders nobody sees skipped),
where lerobot-eval's is hard (a new simulator each episode); both give the same episode, state for state, so each
(suite, task) has an env per reset kind and rows do not say which ran.

Graded progress (graftcache.rollout.graded): the same render callback reads the simulator's state after the reset and
after every step, and the episode's states are measured when it ends. A perturbed episode
(graftcache.rollout.perturb): the env is wrapped (PerturbedReset) so that lerobot-eval's reset to the init state is
followed by the target's seeded offset and settling, before the rollout's first policy step.

The simulator's libraries announce their set-up in every process, for every suite and env they build (robosuite's
macro-file warning at import, LIBERO's task-order line per suite, lerobot's env-building lines): twelve envs in a
team of workers made a quarter of a run's log. Those lines (CHATTER) go to the debug logger SIMULATOR_LOG instead,
filtered here, where every process (a team worker too) imports the simulator and builds its suites and envs
(`simulator_chatter`); any other line they print passes as it is.
"""

from __future__ import annotations

import importlib.util
import io
import logging
import multiprocessing
import re
import sys
import time
import warnings
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager, redirect_stdout
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from graftcache.errors import RolloutError
from graftcache.rollout import seam
from graftcache.rollout.episodes import Episode, Outcome, Suite
from graftcache.rollout.graded import State, measure, target_of

#: the observation size of LIBERO's datasets (lerobot's env defaults to 360)
OBSERVATION_SIZE = 256
INSTALL = "run `make setup-libero` (scripts/setup.sh libero) to install it"
#: torch's intra-op threads while an episode's policy runs, whatever `rollout --workers` is: the rows of N workers are
#: those of one (a thread count may change a reduction's order, hence an action, hence the episode), and N workers
#: on N cores do not spin against each other. The cost is small: the env step, not the policy, takes most of an
#: episode (benchmarks/bench_rollout.py measures both).
POLICY_THREADS = 1
#: The simulator's set-up announcements (see the module docstring): robosuite's three macro-file lines, LIBERO's
#: task order, lerobot's create_envs lines.
CHATTER = re.compile(r"(No private macro file found!|It is recommended to use a private macro file|To setup, run: "
                     r"python \S*setup_macros\.py|\[info\] using task orders |Creating LIBERO envs \||Restricting to "
                     r"task_ids=|Built vec env \|)")
#: Where CHATTER goes, at debug level (shown only where a user configures logging to show it).
SIMULATOR_LOG = logging.getLogger("graftcache.simulator")
#: robosuite's own logger (robosuite.utils.log_utils.DefaultLogger), which its import warns through
ROBOSUITE_LOG = "robosuite_logs"


def _demoted(record: logging.LogRecord) -> bool:
    """A logger filter: a CHATTER record goes to SIMULATOR_LOG at debug level instead of robosuite's handlers."""
    message = record.getMessage()
    if CHATTER.match(message):
        SIMULATOR_LOG.debug(message)
        return False
    return True


class _ChatterFilter(io.TextIOBase):
    """A stdout writing each whole line to `out`, but CHATTER lines to SIMULATOR_LOG at debug level."""

    def __init__(self, out: Any) -> None:
        self.out, self.pending = out, ""

    def write(self, text: str) -> int:
        *lines, self.pending = (self.pending + text).split("\n")
        for line in lines:
            self._line(line, "\n")
        return len(text)

    def _line(self, line: str, end: str) -> None:
        if CHATTER.match(line):
            SIMULATOR_LOG.debug(line)
        else:
            self.out.write(line + end)

    def flush(self) -> None:
        if self.pending:
            self._line(self.pending, "")
            self.pending = ""
        self.out.flush()


@contextmanager
def simulator_chatter() -> Iterator[None]:
    """Inside the block, the simulator's CHATTER goes to SIMULATOR_LOG: robosuite's logger filtered (from then on:
    it warns once per process, at import), stdout's lines too."""
    logging.getLogger(ROBOSUITE_LOG).addFilter(_demoted)  # added once however often (Filterer skips a repeat)
    out = _ChatterFilter(sys.stdout)
    try:
        with redirect_stdout(out):
            yield
    finally:
        out.flush()


def require_simulator() -> None:
    """Refuse, in one line naming how to install it, an environment without lerobot's LIBERO env."""
    for module in ("libero", "robosuite", "mujoco"):
        if importlib.util.find_spec(module) is None:
            raise RolloutError(f"the LIBERO simulator is not installed (no Python module {module}); {INSTALL}")
    try:
        with warnings.catch_warnings(), simulator_chatter():  # robosuite's source has an invalid escape: a
            warnings.simplefilter("ignore", SyntaxWarning)  # SyntaxWarning where no .pyc is cached (uv installs none)
            import lerobot.envs.libero  # noqa: F401  (imports hf-libero, which prompts on stdin without its config)
    except EOFError:
        raise RolloutError("hf-libero asked for its config on stdin ($LIBERO_CONFIG_PATH/config.yaml, default "
                           f"~/.libero, is missing); {INSTALL}, which writes it") from None
    except ImportError as e:
        raise RolloutError(f"the LIBERO simulator cannot be imported ({e}); {INSTALL}") from None


@contextmanager
def quiet_inner_bars() -> Iterator[None]:
    """lerobot's rollout draws a bar of its own per episode; off a terminal (a log) it would write a redraw per step,
    so it is disabled there and the rollout's own sparse lines remain (graftcache.progress); in a team worker too
    (graftcache.rollout.workers), where N of them would fight over the rollout's own bar."""
    if sys.stderr.isatty() and multiprocessing.parent_process() is None:
        yield
        return
    with seam.inner_bars_off():
        yield


@contextmanager
def policy_threads() -> Iterator[None]:
    """torch at POLICY_THREADS intra-op threads inside the block, the process's own count again after it."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(POLICY_THREADS)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def record_frame(frames: list[np.ndarray], env: Any) -> None:
    """lerobot's rollout's render callback: keep the frame lerobot-eval's (eval_policy's render_frame) would keep
    of a one-env vector env."""
    import gymnasium as gym

    frames.append(env.envs[0].render() if isinstance(env, gym.vector.SyncVectorEnv) else env.call("render")[0])


def problem_of(env: Any) -> Any:
    """LIBERO's problem env (the robosuite env built from the task's BDDL) inside lerobot's one-env vector env:
    LiberoEnv -> hf-libero's OffScreenRenderEnv -> its env."""
    return seam.problem(env.envs[0])


def observe(states: list[State], frames: list[np.ndarray] | None, env: Any) -> None:
    """lerobot's rollout's render callback (after the reset and after every step): the simulator's state for the
    graded measures, and the frame when recording."""
    if frames is not None:
        record_frame(frames, env)
    sim = problem_of(env)
    states.append(seam.read_state(sim, target_of(sim)))


class LiberoSimulator:
    """graftcache.rollout.episodes.Simulator over lerobot's LIBERO env. `exports`: where cells are exported (one
    folder per run_id, reused when it holds the run's export); `results`, `cache`, `runs`: as `graftcache export`
    takes them. `max_steps`: the step limit, None for lerobot's episode length of each suite. `videos`: record each
    episode's frames (Outcome.frames)."""

    def __init__(self, results: str | Path, exports: Path, *, cache: str | None, runs: str | None,
                 max_steps: int | None, videos: bool = False, log=print) -> None:
        require_simulator()
        self.results, self.exports, self.cache, self.runs = results, exports, cache, runs
        self.max_steps, self.videos, self.log = max_steps, videos, log
        self._envs: dict[tuple[str, int, str], Any] = {}
        self._cell: tuple[str, tuple[Any, ...]] | None = None  # (run_id, its policy and processors): `loaded`

    def suite(self, name: str) -> Suite:
        from lerobot.envs.libero import TASK_SUITE_MAX_STEPS

        with simulator_chatter():
            n_tasks = seam.suite_tasks(name)
        return Suite(n_tasks=n_tasks, max_steps=self.max_steps or TASK_SUITE_MAX_STEPS[name])

    def export(self, row: Mapping[str, Any]) -> Path:
        """The cell's export folder, written on first use (graftcache export writes it whole or not at all, and a
        rollout running beside this one may write it first). A folder there that is not the run's complete export is
        refused, as `graftcache export` refuses it: exports/ may hold what a person put there."""
        from graftcache.export.bundle import export_run

        return export_run(row["run_id"], self.results, self.exports / row["run_id"], cache=self.cache, runs=self.runs,
                          reuse=True, log=self.log)

    def env_config(self, suite: str, task: int, reset: str = "hard") -> Any:
        from lerobot.envs.factory import make_env_config

        return make_env_config("libero", task=suite, task_ids=[task], episode_length=self.max_steps,
                               observation_height=OBSERVATION_SIZE, observation_width=OBSERVATION_SIZE,
                               hard_reset=reset == "hard")

    def env(self, suite: str, task: int, reset: str = "hard") -> Any:
        """The one-env vector env of (suite, task) resetting as `reset` says (graftcache.rollout.request.RESETS),
        built once per process, its env wrapped to perturb the scene of a perturbed episode and to skip a soft
        reset's unseen renders (graftcache.rollout.perturb.PerturbedReset)."""
        from graftcache.rollout.perturb import PerturbedReset

        if (suite, task, reset) not in self._envs:
            with simulator_chatter():
                vector = self.env_config(suite, task, reset).create_envs(n_envs=1)[suite][task]
            vector.envs[0] = PerturbedReset(vector.envs[0], soft=reset == "soft")
            self._envs[suite, task, reset] = vector
        return self._envs[suite, task, reset]

    def loaded(self, row: Mapping[str, Any], suite: str, task: int) -> tuple[Any, ...]:
        """The cell's policy and its four processors, loaded as lerobot-eval loads them; the last cell's are kept, so
        that a team worker (graftcache.rollout.workers), handed a cell's episodes one call at a time, loads it once."""
        if self._cell is not None and self._cell[0] == row["run_id"]:
            return self._cell[1]
        from lerobot.configs.policies import PreTrainedConfig
        from lerobot.envs.factory import make_env_pre_post_processors
        from lerobot.policies.factory import make_policy, make_pre_post_processors

        import graftcache.export.configuration_graftcache  # noqa: F401  (registers the policy type, as the plugin does)
        import graftcache.export.processors  # noqa: F401  (registers the export's processor steps)

        self._cell = None  # the previous cell's policy is freed before the next one loads
        folder = self.export(row)
        config = PreTrainedConfig.from_pretrained(folder)
        config.pretrained_path = str(folder)
        env_config = self.env_config(suite, task)
        policy = make_policy(config, env_cfg=env_config, rename_map={})
        policy.eval()
        pre, post = make_pre_post_processors(
            policy_cfg=config, pretrained_path=str(folder),
            preprocessor_overrides={"device_processor": {"device": str(policy.config.device)},
                                    "rename_observations_processor": {"rename_map": {}}})
        env_pre, env_post = make_env_pre_post_processors(env_cfg=env_config, policy_cfg=config)
        self._cell = (row["run_id"], (policy, pre, post, env_pre, env_post))
        return self._cell[1]

    def run(self, row: Mapping[str, Any], episodes: Sequence[Episode]) -> Iterator[Outcome]:
        import torch
        from lerobot.scripts.lerobot_eval import rollout
        from lerobot.utils.random_utils import set_seed

        from graftcache.rollout.perturb import Perturbation

        first = episodes[0]
        with policy_threads():
            policy, pre, post, env_pre, env_post = self.loaded(row, first.suite, first.task_index)
            with quiet_inner_bars(), torch.no_grad():
                for episode in episodes:
                    env = self.env(episode.suite, episode.task_index, episode.reset)
                    scene = env.envs[0]
                    index, init_state = seam.start_from(scene, episode.episode)  # lerobot-eval's k-th reset
                    scene.perturbation = (Perturbation(init_state, episode.perturbation_m, episode.seed,
                                                       episode.task_index) if episode.perturbation_m else None)
                    set_seed(episode.seed)
                    frames: list[np.ndarray] | None = [] if self.videos else None
                    states: list[State] = []
                    start = time.perf_counter()
                    data = rollout(env=env, policy=policy, env_preprocessor=env_pre, env_postprocessor=env_post,
                                   preprocessor=pre, postprocessor=post, seeds=[episode.seed],
                                   render_callback=partial(observe, states, frames))
                    seconds = time.perf_counter() - start
                    done = int(torch.argmax(data["done"][0].to(int)))  # eval_policy's first done step
                    yield Outcome(success=bool(data["success"][0, : done + 1].any()), steps=done + 1,
                                  seconds=seconds, init_state=index,
                                  frames=np.stack(frames[: done + 2]) if frames is not None else None,  # all of them
                                  fps=env.unwrapped.metadata["render_fps"] if self.videos else None,
                                  graded=measure(target_of(problem_of(env)), states[: done + 2]),
                                  target_offset_m=(float(scene.offset[0]), float(scene.offset[1])))

    def close(self) -> None:
        self._cell = None
        for env in self._envs.values():
            env.close()
        self._envs.clear()
