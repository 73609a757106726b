"""`graftcache train-tiny`: train a tiny backbone (all parameters, its own vision tower, on pixels).

The frozen-backbone diagnostic is only meaningful on a backbone whose image tokens matter. No
released backbone weights can be fetched here, so `graftcache train-tiny` trains lerobot's
own policy classes at tiny sizes on a LeRobot dataset (the bundled LIBERO sample by default) with
the policy's own flow loss. This is the one place outside stage 1 that decodes video: it trains the
backbone, not a graft. The result is a regular lerobot checkpoint folder (safetensors + processors
with the dataset's normalisation statistics), keyed by dataset content and training recipe and
reproducible from the seed, so `--policy tiny` finds it again.
"""

from __future__ import annotations

import functools
import json
import math
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path

import numpy as np
import polars as pl
import torch

from graftcache.backbones import get_backbone
from graftcache.backbones.tiny import TinyBuild
from graftcache.backbones.tiny_record import policy_dir, read_record, write_record
from graftcache.backbones.tower_encoder import policy_pixels
from graftcache.datasets import DatasetMeta, open_dataset
from graftcache.errors import BackboneError, DatasetError
from graftcache.file_lease import FileLease
from graftcache.fit.data import action_chunks
from graftcache.fit.lookup import dataset_identity
from graftcache.fit.loop import optimise
from graftcache.progress import progress
from graftcache.requests import DEFAULT_TINY_TRAIN, TinyTrainConfig
from graftcache.runtime import resolve_compute_dtype, resolve_device, resolve_dtype, set_main_threads
from graftcache.store import cache_root

__all__ = ["DEFAULT_TINY_TRAIN", "TinyTrainConfig", "dataset_stats", "train_tiny", "warmup_cosine"]


def warmup_cosine(steps: int, warmup: float) -> Callable[[int], float]:
    """LR multiplier per step: linear warm-up over max(1, warmup * steps) steps, then cosine to 0.

    Defined for every step count >= 1 (torch's OneCycleLR divides by zero for e.g. 10 steps at 10% warm-up).
    """
    ramp = max(1, round(warmup * steps))

    def factor(step: int) -> float:
        if step < ramp:
            return (step + 1) / ramp
        rest = max(1, steps - ramp)
        return 0.5 * (1.0 + math.cos(math.pi * min(1.0, (step - ramp + 1) / rest)))

    return factor


def dataset_stats(table: pl.DataFrame) -> dict[str, dict[str, torch.Tensor]]:
    """lerobot-format normalisation statistics of state and action (mean/std/min/max/q01/q99)."""
    out = {}
    for key, col in (("observation.state", "state"), ("action", "action")):
        x = np.stack(table[col].to_numpy()).astype(np.float64)
        out[key] = {
            "mean": x.mean(0), "std": np.maximum(x.std(0), 1e-6), "min": x.min(0), "max": x.max(0),
            "q01": np.quantile(x, 0.01, axis=0), "q99": np.quantile(x, 0.99, axis=0),
        }
        out[key] = {k: torch.as_tensor(v, dtype=torch.float32) for k, v in out[key].items()}
    return out


@functools.lru_cache(maxsize=1)
def _decode_all(dataset: str, cameras: tuple[str, ...], size: int, log: Callable[[str], None]):
    """Every frame of every camera, resized once to `size` (uint8 [N, 3, size, size]), in dataset order.

    Kept for the next call with the same arguments (a sweep trains both tiny backbones on one dataset)."""
    source = open_dataset(dataset)
    episodes = [e.index for e in source.meta.episodes]
    frames: dict[str, list[torch.Tensor]] = {c: [] for c in cameras}
    for ep in progress(episodes, desc="decode", unit="episode", leave=False):
        decoded = source.decode_episode(ep, list(cameras))
        for c in cameras:
            frames[c].append(policy_pixels(torch.from_numpy(decoded[c]), size))
    table = source.lowdim(episodes).sort(["episode_index", "frame_index"])
    log(f"decoded {table.height} frames x {len(cameras)} cameras from {source.meta.root}")
    return source, {c: torch.cat(v) for c, v in frames.items()}, table


def _require_finite(backbone: str, policy: torch.nn.Module, losses: list[float], cfg: TinyTrainConfig) -> None:
    """Refuse to save a policy that training broke (a NaN/inf loss or weight, from an --lr or --weight-decay its
    steps diverge under): saved, it would be a checkpoint saying nothing about it, found again by every later
    `--policy tiny` and grafted onto."""
    bad = next((i for i, loss in enumerate(losses) if not math.isfinite(loss)), None)
    if bad is None and all(torch.isfinite(p).all() for p in policy.parameters()):
        return
    when = (f"its loss was {losses[bad]} at step {bad + 1} of {cfg.steps}" if bad is not None else
            f"its weights hold NaN/inf after {cfg.steps} step(s)")
    raise BackboneError(f"train-tiny {backbone}: training diverged ({when}, lr {cfg.lr}, weight_decay "
                        f"{cfg.weight_decay}); nothing saved: lower --lr or --weight-decay")


def _unfreeze_all(policy: torch.nn.Module) -> None:
    """train-tiny trains everything: lift lerobot's default freezing flags and grads."""
    for module in policy.modules():
        for flag in ("freeze_vision_encoder", "train_expert_only"):
            if hasattr(module, flag) and isinstance(getattr(module, flag), bool):
                setattr(module, flag, False)
    for p in policy.parameters():
        p.requires_grad_(True)


def _cameras(cfg: TinyTrainConfig, meta: DatasetMeta) -> tuple[TinyTrainConfig, tuple[str, ...]]:
    """The cameras the policy will see (`cfg.cameras`, default all of the dataset's, in its order), and `cfg` with
    `cameras` None when they are exactly that default, so one policy has one key however it was asked for."""
    cameras = cfg.cameras or meta.cameras
    unknown = [c for c in cameras if c not in meta.cameras]
    if unknown:
        raise DatasetError(f"{meta.root}: camera {unknown[0]!r} not in dataset; available: {', '.join(meta.cameras)}")
    return replace(cfg, cameras=None if tuple(cameras) == meta.cameras else tuple(cameras)), tuple(cameras)


def _reusable(folder: Path, backbone: str, identity: dict, cfg: TinyTrainConfig, force: bool) -> bool:
    """Whether `folder` already holds the checkpoint asked for. A folder holding another backbone's checkpoint is
    refused whatever `force` says (retraining would mix two policies' files); one trained on another dataset or
    recipe is refused unless `force` (retrain it there)."""
    if not (folder / "config.json").exists():
        return False
    record = read_record(folder)
    held = record.get("backbone") if record else _config_type(folder)
    if held != backbone:
        raise BackboneError(f"{folder} holds a {held or 'non-lerobot'} checkpoint, not a tiny {backbone}: pass "
                            f"another --out for {backbone} (or remove the folder)")
    if force:
        return False
    if record is None or record.get("dataset_identity") != identity or \
            record.get("config") != cfg.as_dict(backbone):
        raise BackboneError(f"{folder} holds a {backbone} checkpoint trained on another dataset or with another "
                            f"recipe (steps, seed, cameras, ...): pass --force to retrain it there, or another --out")
    return True


def _config_type(folder: Path) -> str | None:
    """The policy type a checkpoint's config.json names (None when it names none or is not JSON)."""
    try:
        value = json.loads((folder / "config.json").read_text()).get("type")
    except (OSError, ValueError, AttributeError):
        return None
    return value if isinstance(value, str) else None


def train_tiny(backbone: str, dataset: str, *, cfg: TinyTrainConfig = DEFAULT_TINY_TRAIN, cache: str | None = None,
               device: str = "cpu", out: str | Path | None = None, force: bool = False,
               log: Callable[[str], None] = print) -> Path:
    """Train (or reuse) the tiny `backbone` on `dataset` (all parameters); returns the checkpoint folder."""
    set_main_threads()
    get_backbone(backbone)  # another lerobot release than the adapters' is refused before any decoding
    dev = resolve_device(device)
    cfg = replace(cfg, compute_dtype=resolve_compute_dtype(cfg.compute_dtype, dev))
    compute = resolve_dtype(cfg.compute_dtype)
    home = cache_root(cache)  # a --cache that cannot be a root is refused before any work
    identity = dataset_identity(dataset)
    cfg, cameras = _cameras(cfg, open_dataset(dataset).meta)
    folder = Path(out) if out else policy_dir(home, backbone, identity, cfg)
    with _checkpoint_lease(folder, backbone, log):
        if _reusable(folder, backbone, identity, cfg, force):
            log(f"reusing tiny {backbone} trained by train-tiny: {folder}")
        else:
            _train(backbone, dataset, folder, cfg=cfg, cameras=cameras, identity=identity, device=dev,
                   compute=compute, log=log)
    return folder


@contextmanager
def _checkpoint_lease(folder: Path, backbone: str, log: Callable[[str], None]) -> Iterator[None]:
    """Held while the checkpoint in `folder` is checked for reuse and trained, so that of two processes (sweeps,
    train-tiny) asking for it at once one trains it and the others wait, then reuse it, rather than loading a
    checkpoint still being written. A place that cannot hold the lease file (read-only: reuse only) goes without."""
    lease = FileLease(folder.with_name(f".{folder.name}.lock"))
    try:
        lease.acquire(on_wait=lambda who: log(f"tiny {backbone} is being trained by {who}: waiting to reuse it"))
    except OSError:
        yield
        return
    try:
        yield
    finally:
        lease.release()


def _train(backbone: str, dataset: str, folder: Path, *, cfg: TinyTrainConfig, cameras: tuple[str, ...],
           identity: dict, device: torch.device, compute: torch.dtype, log: Callable[[str], None]) -> None:
    """Train the tiny `backbone` on `dataset` (all parameters) and save it with its record in `folder`."""
    t0 = time.perf_counter()
    source, frames, table = _decode_all(dataset, cameras, cfg.image_size, log)
    meta = source.meta
    tiny = TinyBuild(cameras=cameras, state_dim=meta.state_dim, action_dim=meta.action_dim, seed=cfg.seed)
    adapter = get_backbone(backbone).load("tiny", device=str(device), dataset_stats=dataset_stats(table), tiny=tiny)
    policy = adapter.policy
    _unfreeze_all(policy)
    n_params = sum(p.numel() for p in policy.parameters())
    log(f"training tiny {backbone} (train-tiny): {n_params:,} parameters, all trainable, {cfg.steps} steps, "
        f"compute {cfg.compute_dtype}")
    episode = table["episode_index"].to_numpy()
    acts, pad = action_chunks(np.stack(table["action"].to_numpy()).astype(np.float32), episode, adapter.chunk_size)
    actions, action_pad = torch.from_numpy(acts), torch.from_numpy(pad)
    state = torch.from_numpy(np.stack(table["state"].to_numpy()).astype(np.float32))
    tasks = [meta.tasks[i] for i in table["task_index"].to_list()]

    mean_state = state.mean(0)

    def draw(generator: torch.Generator) -> dict:
        """A batch of frames drawn with replacement (decoded frames are all in memory here); with `state_dropout`,
        a share of them read the mean state, so the policy must find where the arm is in its cameras."""
        pos = torch.randint(0, len(table), (cfg.batch_size,), generator=generator)
        raw = {f"observation.images.{c}": frames[c][pos].float() / 255.0 for c in tiny.cameras}
        seen = state[pos]
        if cfg.state_dropout:  # no draw at 0: the batches of recipes from before the setting stay the same
            dropped = torch.rand(cfg.batch_size, generator=generator) < cfg.state_dropout
            seen = torch.where(dropped[:, None], mean_state, seen)
        raw.update({"observation.state": seen, "action": actions[pos], "action_is_pad": action_pad[pos],
                    "task": [tasks[int(i)] for i in pos]})
        return raw

    opt = torch.optim.AdamW([p for p in policy.parameters()], lr=cfg.lr, weight_decay=cfg.weight_decay)
    losses = optimise(adapter, draw, steps=cfg.steps, batch_size=cfg.batch_size, optimizer=opt,
                      scheduler=torch.optim.lr_scheduler.LambdaLR(opt, warmup_cosine(cfg.steps, cfg.warmup)),
                      clip_norm=1.0, generator=torch.Generator().manual_seed(cfg.seed), dtype=compute,
                      desc=f"train-tiny {backbone}")
    _require_finite(backbone, policy, losses, cfg)
    adapter.save(folder)
    record = {"backbone": backbone, "dataset": str(dataset), "dataset_root": str(meta.root),
              "dataset_identity": identity, "cameras": list(cameras),
              "config": cfg.as_dict(backbone), "final_loss": float(np.mean(losses[-max(1, cfg.steps // 10):])),
              "wall_s": time.perf_counter() - t0, "random_init": True,
              "note": "tiny architecture, random init, trained by graftcache train-tiny (not released weights)"}
    write_record(folder, record)
    log(f"saved tiny {backbone} trained by train-tiny to {folder} (final loss {record['final_loss']:.4f}, "
        f"{record['wall_s']:.0f}s)")
