"""Every reach of graftcache's past the public API of lerobot, hf-libero and robosuite, in one module: a private
attribute read, an attribute of theirs written, a function of theirs patched. The rest of graftcache calls the
functions here (tests/rollout/test_seam.py fails on a reach anywhere else; lerobot's VLAs, which the backbone
adapters under graftcache/backbones/ reach into, are a house of their own: each backbone declares its reaches,
graftcache.backbones.spec.BackboneSpec.lerobot_reaches, which tests/backbones/test_lerobot_reaches.py checks against
its code and the installed lerobot). Their insides move between releases
without notice, so the versions this module was read in (graftcache.upstream.WRITTEN_AGAINST, one table for both
houses) are checked as it is imported: another installed version is refused in one line naming both and the pin,
before any episode, rather than failing deep in one with a traceback.

What is reached, and why:
- lerobot's LiberoEnv: its hf-libero env (`_env`, built by `_ensure_env`), its init states (`_init_states`) and the
  counter its reset reads them by (`init_state_id`: episode k starts from init state k whatever ran before), its
  formatting of a raw observation (`_format_raw_obs`, for a perturbed scene's), its settling steps and cameras; the
  suites it is built from (`lerobot.envs.libero._get_suite`); lerobot-eval's per-episode bar
  (`lerobot.scripts.lerobot_eval.trange`, patched off).
- LIBERO's problem env (robosuite's, built from the task's BDDL): the grasp check and the goal predicates the graded
  measures read (`_check_grasp`, `_eval_predicate`).
- robosuite's MjSim render (patched, for the renders nobody sees) and each gripper's held command.

The fast reset (`graftcache rollout --reset soft`) is two things. lerobot's own soft reset (its LIBERO config's
`hard_reset=False`: robosuite's `sim.reset()` instead of a new MjSim and render context each episode; the init state
is set over it either way). And renders skipped: lerobot's reset renders both cameras on robosuite's reset, on setting
the init state and on each of its settling no-op steps, and only the last step's images become the observation. The
physics never reads an image, so skipping the others leaves every state as it was; `renders_from` gates the MjSim's
render by robosuite's step counter, which a soft reset keeps counting on the same MjSim (a hard reset builds a new
one, whose renders it cannot reach: there the gate is not installed). A soft reset that rebuilt the simulator, or
whose observation was not rendered (graftcache.rollout.perturb.PerturbedReset checks `Renders`), is refused rather
than feeding the policy a blank image.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import numpy as np

from graftcache.errors import RolloutError
from graftcache.rollout.graded import State
from graftcache.upstream import WRITTEN_AGAINST, refuse_others

#: the simulator's libraries, whose releases this module was read in (graftcache.upstream.WRITTEN_AGAINST)
LIBRARIES = ("lerobot", "hf-libero", "robosuite")


def check_versions() -> None:
    """Refuse, in one line naming both versions and the pin, an installed lerobot, hf-libero or robosuite other than
    the one this module was read in (graftcache.upstream.refuse_others)."""
    refuse_others(LIBRARIES, "graftcache/rollout/seam.py", RolloutError)


check_versions()


def suite_tasks(name: str) -> int:
    """The number of tasks of LIBERO suite `name`, in the benchmark lerobot builds its envs from."""
    from lerobot.envs.libero import _get_suite

    return len(_get_suite(name).tasks)


def libero_env(env: Any) -> Any:
    """hf-libero's OffScreenRenderEnv inside lerobot's LiberoEnv `env` (any gym wrapper of it), built on first
    use as lerobot's reset builds it (LiberoEnv._ensure_env, LiberoEnv._env)."""
    lerobot_env = env.unwrapped
    lerobot_env._ensure_env()
    return lerobot_env._env


def problem(env: Any) -> Any:
    """LIBERO's problem env (the robosuite env built from the task's BDDL) inside lerobot's LiberoEnv `env`."""
    return libero_env(env).env


def settle_steps(env: Any) -> int:
    """The no-op steps lerobot's reset settles the scene with (LiberoEnv.num_steps_wait)."""
    return int(env.unwrapped.num_steps_wait)


def cameras(env: Any) -> int:
    """The camera images an observation of `env` holds (lerobot's LiberoEnv.camera_name)."""
    return len(env.unwrapped.camera_name)


def start_from(env: Any, k: int) -> tuple[int, np.ndarray]:
    """Make lerobot's next reset of `env` the k-th reset of a freshly built env, as lerobot-eval's episode k is:
    LiberoEnv.init_state_id, which its reset reads and then advances, set to k. Returns the init state that reset
    sets: its index among the task's official init states as the env loaded them (k modulo their number), and it."""
    lerobot_env = env.unwrapped
    states = lerobot_env._init_states
    lerobot_env.init_state_id = k
    return k % len(states), states[k % len(states)]


def observation(env: Any, raw: dict) -> Any:
    """lerobot's observation of hf-libero's raw observation `raw` (LiberoEnv._format_raw_obs), as its reset and
    step return it."""
    return env.unwrapped._format_raw_obs(raw)


@contextmanager
def inner_bars_off() -> Iterator[None]:
    """Inside, lerobot's rollout draws no bar of its own: lerobot-eval's trange, which it calls once per episode,
    made disabled (over the arguments it passes)."""
    from lerobot.scripts import lerobot_eval
    from tqdm import trange

    lerobot_eval.trange = lambda *args, **kwargs: trange(*args, **{**kwargs, "disable": True})
    try:
        yield
    finally:
        lerobot_eval.trange = trange


def read_state(sim: Any, target: str) -> State:
    """The State of LIBERO's problem env `sim` (`problem`) now, read from MuJoCo's data: the grip site's and the
    target body's world positions (what robosuite's `robot0_eef_pos` and `<target>_pos` observe), robosuite's own
    `_check_grasp` over both fingers' whole geoms (finger and pad) against the target's contact geoms, and LIBERO's
    own `_eval_predicate` on each goal predicate (what `_check_success` conjoins)."""
    data = sim.sim.data
    robot = sim.robots[0]
    fingers = robot.gripper.important_geoms
    goals = sim.parsed_problem["goal_state"]
    return State(eef=tuple(float(v) for v in data.site_xpos[robot.eef_site_id]),
                 target=tuple(float(v) for v in data.body_xpos[sim.obj_body_id[target]]),
                 grasping=bool(sim._check_grasp(gripper=[fingers["left_finger"], fingers["right_finger"]],
                                                object_geoms=sim.get_object(target))),
                 goals_met=sum(bool(sim._eval_predicate(g)) for g in goals), goals=len(goals))


@dataclass
class Renders:
    """What `renders_from` let through: `done`, the camera images rendered; `skipped`, those answered blank."""

    done: int = 0
    skipped: int = 0


@contextmanager
def renders_from(env: Any, step: int | None) -> Iterator[Renders]:
    """Inside, the camera renders of `env`'s MjSim (robosuite's env.sim.render, which its camera sensors call)
    are answered with a blank image while robosuite's step counter (env.timestep: 0 after a reset, the settling or
    policy step in progress after) is below `step` (None: all of them), and rendered from it on. Blank images
    must never reach a policy: the caller checks `Renders.done` against the images it keeps. The MjSim must outlive
    the block (a soft reset: a hard one replaces it, and the gate with it)."""
    problem_env = problem(env)
    sim, counts = problem_env.sim, Renders()
    render, own = sim.render, "render" in vars(sim)

    def gated(*args: Any, camera_name: str, width: int, height: int, depth: bool = False, **kwargs: Any) -> Any:
        if step is not None and problem_env.timestep >= step:
            counts.done += 1
            return render(*args, camera_name=camera_name, width=width, height=height, depth=depth, **kwargs)
        if depth or args or kwargs:
            raise RolloutError(f"robosuite asked for a render graftcache cannot skip (depth or segmentation of "
                               f"{camera_name}); roll out with --reset hard")
        counts.skipped += 1
        return np.zeros((height, width, 3), np.uint8)

    sim.render = gated
    try:
        yield counts
    finally:
        rebuilt = problem_env.sim is not sim
        if own:
            sim.render = render
        else:
            del sim.render
    if rebuilt:
        raise RolloutError("the simulator was rebuilt during a soft reset (the env reset hard: lerobot "
                           f"{WRITTEN_AGAINST['lerobot']}'s hard_reset=False no longer holds); roll out with "
                           "--reset hard")


@contextmanager
def frames_reused(sim: Any) -> Iterator[None]:
    """Inside, each camera view robosuite's MjSim `sim` is asked for is rendered once and that image returned again:
    for steps whose images nobody keeps (a perturbation's settling before its last step). The physics never reads
    an image, so the state evolves exactly as it would, and rendering is most of a step's cost (2 cameras at 256 px,
    read back from an offscreen context on CPU). lerobot's reset, whose scene a perturbation replaces, renders
    nothing with a soft reset (`renders_from`); a hard one builds a new MjSim, out of reach."""
    render, own = sim.render, "render" in vars(sim)
    seen: dict[Any, Any] = {}

    def once(*args: Any, **kwargs: Any) -> Any:
        key = (args, tuple(sorted(kwargs.items())))
        if key not in seen:
            seen[key] = render(*args, **kwargs)
        return seen[key]

    sim.render = once
    try:
        yield
    finally:
        if own:
            sim.render = render
        else:
            del sim.render


def release_grippers(env: Any) -> None:
    """Forget the gripper command each robot's gripper holds (robosuite's gripper.current_action, which its grippers
    integrate each step), as a hard reset's newly built grippers start: robosuite 1.4.0's soft reset keeps the last
    episode's, so the settling steps would open the gripper from where the last episode left it."""
    for robot in libero_env(env).robots:
        robot.gripper.current_action = np.zeros(robot.gripper.dof)
