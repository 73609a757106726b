#!/usr/bin/env python
"""Pack the npz episodes from data/render_sample.py into a LeRobot v3.0 dataset with lerobot's own writer.

Runs in the project venv, offline: LeRobotDataset.create -> add_frame -> save_episode -> finalize, in
video mode (AV1 mp4 per camera, like lerobot/libero). Afterwards it reopens the result with
LeRobotDataset and checks episode/frame/task counts and that decoded frames match the rendered ones.

Why the keyframe interval is set: lerobot's default (g=2) roughly doubles the file size of these short
clips and the sample must stay small enough to commit, so `create` gets an RGBEncoderConfig with our
g / crf / preset (lerobot 0.6; the committed sample was packed with lerobot 0.4.4, whose writer had the
same settings hard-wired and was patched for the packing). Every episode still starts on a keyframe
(each is encoded separately before lerobot concatenates them), so per-episode seeking is unaffected;
only random access inside an episode decodes a few more frames.
"""

from __future__ import annotations

import os

os.environ.setdefault("HF_HUB_OFFLINE", "1")

import argparse  # noqa: E402
import json  # noqa: E402
import shutil  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402
from lerobot.configs.video import RGBEncoderConfig  # noqa: E402
from lerobot.datasets.lerobot_dataset import LeRobotDataset  # noqa: E402
from tqdm import tqdm  # noqa: E402

from devtools.scheduling import scheduling_kept  # noqa: E402

CAMERAS = {"observation.images.image": "image", "observation.images.image2": "image2"}  # key -> npz array
STATE_NAMES = ["eef_x", "eef_y", "eef_z", "eef_axis_angle_x", "eef_axis_angle_y", "eef_axis_angle_z",
               "gripper_qpos_left", "gripper_qpos_right"]
ACTION_NAMES = ["dx", "dy", "dz", "droll", "dpitch", "dyaw", "gripper"]
MIN_PSNR_DB = 28.0  # decoded vs rendered frame; AV1 at the default crf gives well above this


def features(size: int) -> dict:
    hwc = {"dtype": "video", "shape": (size, size, 3), "names": ["height", "width", "channel"]}
    return {
        **{key: dict(hwc) for key in CAMERAS},
        "observation.state": {"dtype": "float32", "shape": (8,), "names": STATE_NAMES},
        "action": {"dtype": "float32", "shape": (7,), "names": ACTION_NAMES},
    }


def pack(manifest: dict, npz_dir: Path, args: argparse.Namespace) -> LeRobotDataset:
    ds = LeRobotDataset.create(repo_id=args.repo_id, fps=10, features=features(manifest["size"]),
                               root=args.out, robot_type="panda", use_videos=True,
                               rgb_encoder=RGBEncoderConfig(vcodec=args.vcodec, g=args.gop, crf=args.crf,
                                                            preset=args.preset),
                               encoder_threads=args.encoder_threads)
    with scheduling_kept():  # SVT-AV1 as root leaves this thread real-time (devtools/scheduling.py)
        for rec in tqdm(manifest["episodes"], desc="packing", unit="ep"):
            z = np.load(npz_dir / rec["file"])
            for t in range(len(z["action"])):
                frame = {key: z[arr][t] for key, arr in CAMERAS.items()}
                ds.add_frame({**frame, "observation.state": z["state"][t], "action": z["action"][t],
                              "task": str(z["task"])})
            ds.save_episode(parallel_encoding=False)  # in-process: the machine is shared anyway
        ds.finalize()
    return ds


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)
    return float("inf") if mse == 0 else 10 * np.log10(255.0**2 / mse)


def verify(manifest: dict, npz_dir: Path, args: argparse.Namespace) -> dict:
    """Reopen with lerobot's reader; compare counts, tasks, low-dim values and decoded frames."""
    episodes = manifest["episodes"]
    ds = LeRobotDataset(args.repo_id, root=args.out)
    expected_frames = sum(r["frames"] for r in episodes)
    assert ds.meta.info["codebase_version"] == "v3.0", ds.meta.info["codebase_version"]
    assert ds.num_episodes == len(episodes), (ds.num_episodes, len(episodes))
    assert ds.num_frames == expected_frames, (ds.num_frames, expected_frames)
    assert set(ds.meta.tasks.index) == {r["task"] for r in episodes}, list(ds.meta.tasks.index)
    worst = float("inf")
    start = 0
    for ep, rec in enumerate(episodes):
        z = np.load(npz_dir / rec["file"])
        for t in (0, rec["frames"] - 1):  # the first and last frame of every episode
            item = ds[start + t]
            assert int(item["episode_index"]) == ep and int(item["frame_index"]) == t, (ep, t)
            assert item["task"] == rec["task"], (ep, item["task"])
            np.testing.assert_allclose(item["action"].numpy(), z["action"][t], atol=1e-6)
            np.testing.assert_allclose(item["observation.state"].numpy(), z["state"][t], atol=1e-6)
            for key, arr in CAMERAS.items():
                decoded = (item[key].permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)
                worst = min(worst, psnr(decoded, z[arr][t]))
        start += rec["frames"]
    assert worst >= MIN_PSNR_DB, f"decoded frames differ from the render: worst PSNR {worst:.1f} dB"
    return dict(episodes=ds.num_episodes, frames=ds.num_frames, tasks=len(ds.meta.tasks),
                worst_psnr_db=round(worst, 1))


def dir_size_mb(path: Path) -> float:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file()) / 2**20


def parse_args() -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("npz_dir", type=Path, help="folder written by render_sample.py (holds manifest.json)")
    p.add_argument("--out", type=Path, default=Path(__file__).resolve().parent / "libero_sample")
    p.add_argument("--repo-id", default="graftcache/libero_sample")
    p.add_argument("--vcodec", default="libsvtav1")
    p.add_argument("--crf", type=int, default=30)
    p.add_argument("--gop", type=int, default=2, help="keyframe interval in frames (lerobot: 2)")
    p.add_argument("--preset", type=int, default=12, help="SVT-AV1 preset, 0 slowest/best .. 13 fastest")
    p.add_argument("--encoder-threads", type=int, default=1)
    return p.parse_args()


def main() -> None:
    args = parse_args()
    torch.set_num_threads(1)
    manifest = json.loads((args.npz_dir / "manifest.json").read_text())
    if args.out.exists():
        if not (args.out / "meta" / "info.json").exists():
            raise SystemExit(f"{args.out} exists and is not a LeRobot dataset; refusing to overwrite it")
        shutil.rmtree(args.out)
    t0 = time.time()
    pack(manifest, args.npz_dir, args)
    # Render provenance (seed, init state, target offset, script plan per episode) next to the data.
    (args.out / "render_manifest.json").write_text(json.dumps(manifest, indent=1))
    pack_s = time.time() - t0
    report = verify(manifest, args.npz_dir, args)
    report.update(size_mb=round(dir_size_mb(args.out), 2), pack_s=round(pack_s, 1), crf=args.crf,
                  gop=args.gop, preset=args.preset)
    print(json.dumps(report))


if __name__ == "__main__":
    main()
