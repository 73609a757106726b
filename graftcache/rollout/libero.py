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

Graded progress (graftcache.rollout.graded): the same render callback (graftcache.rollout.render_callback.observe)
reads the simulator's state after the reset and after every step, and the episode's states are measured when it ends.
A perturbed episode (graftcache.rollout.perturb): the env is wrapped (PerturbedReset) so that lerobot-eval's reset to
the init state is followed by the target's seeded offset and settling, before the rollout's first policy step.

The process's set-up around the simulator (its libraries checked, their chatter quieted, the policy's threads):
graftcache.rollout.simulator_setup.
"""

from __future__ import annotations

import time
from collections.abc import Iterator, Mapping, Sequence
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from graftcache.rollout import seam
from graftcache.rollout.episodes import Episode, Outcome, Suite
from graftcache.rollout.graded import State, measure, target_of
from graftcache.rollout.render_callback import observe, problem_of
from graftcache.rollout.simulator_setup import policy_threads, quiet_inner_bars, require_simulator, simulator_chatter

#: the observation size of LIBERO's datasets (lerobot's env defaults to 360)
OBSERVATION_SIZE = 256


class LiberoSimulator:
    """graftcache.rollout.episodes.Simulator over lerobot's LIBERO env. `exports`: where cells are exported (one
    folder per run_id, reused when it holds the run's export); `results`, `cache`, `runs`: as `graftcache export`
    takes them. `max_steps`: the step limit, None for lerobot's episode length of each suite. `videos`: record each
    episode's frames (Outcome.frames). `device`: where each cell's policy runs (its export says cpu:
    lerobot's make_policy builds it on the config's device, and the processors move each batch there)."""

    def __init__(self, results: str | Path, exports: Path, *, cache: str | None, runs: str | None,
                 max_steps: int | None, videos: bool = False, device: str = "cpu", log=print) -> None:
        require_simulator()
        self.results, self.exports, self.cache, self.runs = results, exports, cache, runs
        self.max_steps, self.videos, self.device, self.log = max_steps, videos, device, log
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
        config.pretrained_path, config.device = str(folder), self.device
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
        from graftcache.runtime import kernels, resolve_device

        first = episodes[0]
        computed_on = kernels(resolve_device(self.device))
        with policy_threads():
            policy, pre, post, env_pre, env_post = self.loaded(row, first.suite, first.task_index)
            with quiet_inner_bars(), torch.no_grad():
                for episode in episodes:
                    env = self.env(episode.suite, episode.task_index, episode.reset)
                    task_env = env.envs[0]
                    index, init_state = seam.start_from(task_env, episode.episode)  # lerobot-eval's k-th reset
                    task_env.perturbation = (Perturbation(init_state, episode.perturbation_m, episode.seed,
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
                                  target_offset_m=(float(task_env.offset[0]), float(task_env.offset[1])),
                                  kernels=computed_on)

    def close(self) -> None:
        self._cell = None
        for env in self._envs.values():
            env.close()
        self._envs.clear()
