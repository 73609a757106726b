"""What each command is asked to do: the request dataclasses, in one light module.

Each field's default lives here and only here: the CLI derives its flags' defaults from these fields
(cli/common.py `default_of`), the sweep recipe's settings tables are these fields, and the range rules
(checks.py) are declared beside them. Nothing here imports torch or the models, so building the CLI's
parser stays cheap.
"""

from __future__ import annotations

import sys
from dataclasses import asdict, dataclass, field
from typing import Any, ClassVar

from graftcache.cameras import SYNTAX, valid_camera_map
from graftcache.checks import EPISODES, FRACTION, NAMES, NON_NEGATIVE, POSITIVE, SEED, SEEDS, SHARD, Checked, Rule
from graftcache.errors import GraftcacheError
from graftcache.pooling import NATIVE, valid_grid_names

#: A camera map's text (graftcache/cameras.py); the CLI's parser names what is wrong with one in more detail.
CAMERA_MAP: Rule = (valid_camera_map, f"must be {SYNTAX}, each policy camera once, each from a camera of its own")


@dataclass(frozen=True)
class ExtractRequest(Checked):
    """Everything `graftcache extract` needs. Fields up to and including `compute_dtype` change the numbers
    (they are part of the cache key, compute_dtype once resolved); the ones after it do not."""

    dataset: str
    encoder: str
    grids: tuple[str, ...] = (NATIVE,)  # grid names: the encoder's own grid unpooled, and/or pooled "HxW" grids
    cameras: tuple[str, ...] | None = None
    episodes: tuple[int, ...] | None = None
    weights: str | None = None
    random_init: bool = False
    seed: int = 0
    policy: str | None = None  # native towers (smolvla-native, pi05-native) come from a policy
    frame_stride: int = 1  # features for frames whose frame_index % frame_stride == 0 (actions stay full rate)
    dtype: str = "fp16"
    compute_dtype: str = "auto"  # resolved per device by runtime.resolve_compute_dtype before anything is keyed
    camera_map: str | None = None  # native towers: policy camera <- dataset camera where names differ (checked only)
    device: str = "cpu"
    batch_size: int = 32
    num_workers: int = 2
    block_frames: int = 256
    shard: tuple[int, int] | None = None  # (i, N): write only shard i of N's blocks (graftcache/extract.py)
    cache: str | None = None
    progress: bool = True
    allow_nonfinite: bool = False  # cache NaN/inf state/action/features instead of refusing (fit then refuses)
    extra_manifest: dict[str, Any] = field(default_factory=dict)

    RULES: ClassVar[dict[str, Rule]] = {"seed": SEED, "batch_size": POSITIVE, "num_workers": NON_NEGATIVE,
                                        "block_frames": POSITIVE, "episodes": EPISODES,
                                        "frame_stride": POSITIVE, "shard": SHARD, "cameras": NAMES,
                                        "camera_map": CAMERA_MAP,
                                        "grids": (valid_grid_names, f"must name grids: {NATIVE} or HxW, e.g. {NATIVE},4x4")}


def _suites() -> tuple[str, ...]:
    from graftcache.datasets.suites import SUITES  # imported on use: the package loads polars

    return SUITES


#: A suite a cache can record (graftcache.datasets.suites.SUITES): a typo is refused before any cache is made.
SUITE: Rule = (lambda v: v in _suites(), lambda: f"is not a suite; choose one of {', '.join(_suites())}")
#: Controls besides the plain graft ("none"), which every request runs anyway: each once.
CONTROL_LIST: Rule = (lambda v: len(set(v)) == len(v) and "none" not in v,
                      "must name each control once, and not none (the plain graft always runs)")


@dataclass(frozen=True)
class FitRequest(Checked):
    """Everything `graftcache fit` needs: one (backbone, encoder, suite) over seeds and controls."""

    backbone: str
    encoder: str
    suite: str
    policy: str = "tiny"
    dataset: str | None = None
    cache_key: str | None = None
    native_cache_key: str | None = None
    camera_map: str | None = None  # "POLICY=CACHE,...": which cache camera feeds each policy camera where names differ
    seeds: tuple[int, ...] = (0, 1, 2)
    controls: tuple[str, ...] = ()
    objective: str = "flow"
    steps: int = 300
    lr: float = 1e-3
    batch_size: int = 16
    buffer_mib: int = 2048  # training features held at once (shuffle buffer; with --num-workers x 2 prefetched blocks;
    # with --num-workers 0, as much again of blocks kept for the next cells)
    eval_fraction: float = 0.2
    eval_split_seed: int = 0
    eval_frames: int | None = None
    num_denoise_steps: int | None = None
    lora_rank: int = 8
    device: str = "cpu"
    num_workers: int = 2  # processes reading the cache ahead of the model (the numbers do not depend on it)
    cells_per_pass: int | None = None  # cells trained together in one pass of the frozen backbone (graftcache/fit/
    # passes.py); None: the measured default for the backbone and device. Rows match one cell at a time within
    # float rounding, and no run_id depends on it
    compute_dtype: str = "auto"  # resolved per device (runtime.resolve_compute_dtype) before it reaches a row
    results: str = "results.parquet"
    out: str | None = None
    cache: str | None = None
    progress: bool = True
    drop_nonfinite: bool = False  # drop frames with NaN/inf (features, state, action chunk) instead of refusing
    accept_numerics_drift: bool = False  # fit caches this environment would compute differently (rows record it)
    command: str = field(default_factory=lambda: " ".join(["graftcache", *sys.argv[1:]]))

    RULES: ClassVar[dict[str, Rule]] = {
        "seeds": SEEDS, "suite": SUITE, "controls": CONTROL_LIST, "steps": POSITIVE, "lr": POSITIVE,
        "batch_size": POSITIVE, "buffer_mib": POSITIVE, "num_workers": NON_NEGATIVE,
        "cells_per_pass": POSITIVE, "eval_fraction": FRACTION, "eval_split_seed": SEED, "eval_frames": POSITIVE,
        "num_denoise_steps": POSITIVE, "lora_rank": POSITIVE,
        "camera_map": CAMERA_MAP,
    }


#: Ray's num_gpus: a share of one GPU (several tasks on one device) or whole GPUs.
GPU_SHARE: Rule = (lambda v: v >= 0 and (v <= 1 or float(v).is_integer()), "must be between 0 and 1 or a whole number")


@dataclass(frozen=True)
class ExecutorSettings(Checked):
    """Where `extract` and `sweep` run their work (graftcache/executors/): in this process, or as Ray tasks on
    a cluster that sees the same cache root and results folder. Nothing here changes a number: the caches,
    run_ids and rows are the same under every executor."""

    executor: str = "local"
    address: str | None = None  # ray: a running cluster ("auto", "ray://head:10001"); None starts one here
    gpus_per_task: float | None = None  # ray: None = 1 when the device is cuda, else 0; a fraction shares a GPU
    cpus_per_task: float = 1.0  # ray: also the task's torch thread count (Ray sets OMP_NUM_THREADS from it)
    shards: int | None = None  # ray extract: tasks per cache; None = as many as the cluster runs at once
    max_retries: int = 3  # ray: reruns of a task whose worker or node died (never of an error the task raised)

    RULES: ClassVar[dict[str, Rule]] = {"gpus_per_task": GPU_SHARE, "cpus_per_task": POSITIVE, "shards": POSITIVE,
                                        "max_retries": NON_NEGATIVE}


@dataclass(frozen=True)
class TileRequest(Checked):
    """What `graftcache tile` builds: a dataset of `preset`'s dimensions, or of `episodes` episodes (and
    `frames` frames; default: the source's mean length times `episodes`) over the source's tasks."""

    source: str
    dest: str
    preset: str | None = None  # a name of graftcache.datasets.tile.PRESETS ("libero": lerobot/libero's counts)
    episodes: int | None = None
    frames: int | None = None
    seed: int = 0  # episode lengths and window positions

    RULES: ClassVar[dict[str, Rule]] = {"episodes": POSITIVE, "frames": POSITIVE, "seed": SEED}

    def __post_init__(self) -> None:
        super().__post_init__()
        if (self.preset is None) == (self.episodes is None):
            raise GraftcacheError("tile needs exactly one of preset and episodes")
        if self.frames is not None and self.episodes is None:
            raise GraftcacheError("frames goes with episodes (a preset fixes its own frame counts)")


@dataclass(frozen=True)
class TinyTrainConfig(Checked):
    """The recipe of `graftcache train-tiny` (it keys the checkpoint folder, with the dataset's identity)."""

    steps: int = 300  # enough for the tiny backbones to use vision on the sample (native beats zero-image)
    batch_size: int = 32
    lr: float = 1e-3
    weight_decay: float = 1e-4
    seed: int = 0
    image_size: int = 128  # frames are resized once to this (>= every tiny tower's input)
    warmup: float = 0.1    # share of the steps with a linear warm-up, then cosine decay to 0
    compute_dtype: str = "auto"  # resolved (runtime.resolve_compute_dtype) before it keys the checkpoint
    cameras: tuple[str, ...] | None = None  # the policy's cameras, in this order; None: all the dataset's, in its order

    RULES: ClassVar[dict[str, Rule]] = {"cameras": NAMES, "steps": POSITIVE, "batch_size": POSITIVE, "lr": POSITIVE,
                                        "weight_decay": NON_NEGATIVE, "seed": SEED, "image_size": POSITIVE,
                                        "warmup": (lambda v: 0 <= v < 1, "must be in [0, 1)")}

    def as_dict(self, backbone: str) -> dict:
        """The recipe as it keys the checkpoint folder. `cameras` None (the dataset's own, the only choice before
        the field existed) is left out, so checkpoints trained before it are found again under their keys."""
        values = asdict(self)
        if values["cameras"] is None:
            del values["cameras"]
        return {"backbone": backbone, **values}


DEFAULT_TINY_TRAIN = TinyTrainConfig()
