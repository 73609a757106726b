"""What each command is asked to do: the request dataclasses, in one light module, and the one home of every
setting.

Each field declares, with `setting(...)` (graftcache/settings.py), everything about it that is used outside
Python: its default, help, flag, choices, range rule (graftcache/checks.py), how its flag's text is read and
written (graftcache/codecs.py; by default from the field's type), and whether a sweep recipe's settings section
may set it (`recipe=False`: the sweep sets it from its product). From these the CLI builds its flags
(graftcache.cli.common.add_flags), the recipe reader its schema (graftcache.recipe), the sweep the command lines
it records (graftcache.sweep.command_line), and `Checked` the checks every construction runs.

Adding a setting is one declaration here. E.g. a FitRequest field

    eval_batch_size: int | None = setting(None, rule=POSITIVE, help="frames scored at once (default: --batch-size)")

is at once `graftcache fit --eval-batch-size N` (an int > 0; `--eval-batch-size 0` is a one-line usage error),
a key of a recipe's [fit] section (type and range checked there too), written into the command lines a sweep
records, and checked whenever a FitRequest is built. A choice is `choices=("auto", "on", "off")`; a switch is a
`bool` field (default False: `--name`; default True: `--no-name`). A field the command sets itself takes
`flag=None`; one the sweep's product sets takes `recipe=False`.

A FitRequest setting that changes the numbers says so in the same declaration: `cell=` puts it in each cell's
identity (graftcache.fit.plan.Cell, hashed into the run_id; `SCHEDULED`: only cells whose objective takes steps),
`shared=True` makes the cells of a backbone pass share it (the pass key), `column=True` gives rows a column of it
(every setting in cells is a column: rows record the whole cell they hash). One added to cells after the identity
version cells hash (graftcache.results.IDENTITY_VERSION) names the results format that adds it and what every
earlier cell held, e.g.

    weight_decay: float = setting(0.0, rule=WEIGHT_DECAY, column=True,
                                  cell=Identity("scheduled", since=6, before=0.0))

so that earlier cells keep their run_ids, earlier rows read as holding 0.0, and results.FORMAT_VERSION becomes 6;
what is left is its use (here: the optimiser graftcache.fit.loop.learner builds).

Nothing here imports torch or the models, so building the CLI's parser stays cheap: choices are plain data, and
help that lists what a heavy module registers is a function the CLI calls only to print help.
"""

from __future__ import annotations

import os
import sys
from dataclasses import asdict, dataclass
from typing import Any

from graftcache import codecs
from graftcache.backbone_registry import BACKBONES, native_name
from graftcache.cameras import SYNTAX, valid_camera_map
from graftcache.checks import (
    EPISODES,
    FRACTION,
    LEARNING_RATE,
    NAMES,
    NON_NEGATIVE,
    POSITIVE,
    SEED,
    SEEDS,
    SHARD,
    WEIGHT_DECAY,
    WORKERS,
    Rule,
)
from graftcache.dtypes import COMPUTE_DTYPES, STORED_DTYPES
from graftcache.lazy import import_string
from graftcache.pooling import UNPOOLED, valid_grid_names
from graftcache.settings import Checked, Identity, Twin, setting

#: A camera map's text (graftcache/cameras.py); the CLI's parser names what is wrong with one in more detail.
CAMERA_MAP: Rule = (valid_camera_map, f"must be {SYNTAX}, each policy camera once, each from a camera of its own")
GRIDS: Rule = (valid_grid_names, f"must name grids: {UNPOOLED} or HxW, e.g. {UNPOOLED},4x4")
CACHE_HELP = "cache root: a folder or an s3:// gs:// az:// URL (default: $GRAFTCACHE_HOME or ~/.cache/graftcache)"
PROGRESS_HELP = "no progress bars or lines"
#: The devices a command's models run on (graftcache.runtime.resolve_device checks one; `rollout --device` takes them
#: too)
DEVICE_HELP = "cpu, cuda or cuda:N"


def compute_dtype(**fit: Any) -> Any:
    """The compute_dtype field of every request that runs a model: resolved per device
    (runtime.resolve_compute_dtype) before anything is keyed or recorded (`fit`: what a fit's cells make of it)."""
    return setting("auto", choices=COMPUTE_DTYPES, **fit,
                   help="model compute precision. auto: bf16 where the device computes it in hardware (CUDA with bf16, "
                   "CPUs with AVX512-BF16/AMX), else fp32. The resolved dtype is recorded in manifests, keys and rows")


@dataclass(frozen=True)
class ExtractRequest(Checked):
    """Everything `graftcache extract` needs. Fields up to and including `compute_dtype` change the numbers
    (they are part of the cache key, compute_dtype once resolved); the ones after it do not."""

    dataset: str = setting(recipe=False, help="local LeRobot dataset folder or a hub repo id in the local HF cache")
    encoder: str = setting(recipe=False, help="registry name (siglip, dinov2-s, mobilenetv2, ...), timm:<name> or "
                           "hf:<id-or-path>")
    grids: tuple[str, ...] = setting(
        (UNPOOLED,), rule=GRIDS, codec=codecs.GRIDS,
        help=f"grids to store: {UNPOOLED} (the encoder's own patch grid, unpooled; `fit` pools it to each backbone's "
        f"token grid as it reads it) and/or pooled HxW grids, e.g. {UNPOOLED},4x4 or 8x8,16x16. {UNPOOLED} and the "
        "encoder's grid spelled out make the same cache")
    cameras: tuple[str, ...] | None = setting(None, rule=NAMES, help="comma-separated camera names (default: all)")
    episodes: tuple[int, ...] | None = setting(None, rule=EPISODES, recipe=False, help="episode subset, e.g. 0-9,20")
    weights: str | None = setting(None, recipe=False, help="local weights file/folder instead of the hub id")
    random_init: bool = setting(False, recipe=False, help="random weights (labelled random-init everywhere)")
    seed: int = setting(0, rule=SEED, recipe=False, help="seed for --random-init")
    policy: str | None = setting(  # native towers (smolvla-native, pi05-native) come from a policy
        None, recipe=False,
        help=lambda: f"policy for native towers ({', '.join(native_name(b) for b in BACKBONES)}): hub id, checkpoint "
        "folder, or 'tiny' (the tiny backbone trained on --dataset by `graftcache train-tiny`)")
    frame_stride: int = setting(  # features for frames whose frame_index % frame_stride == 0 (actions full rate)
        1, rule=POSITIVE, metavar="K",
        help="features for every K-th frame of each episode (frame_index %% K == 0); actions stay at the full rate "
        "for action chunks. Part of the cache key (1: every frame)")
    storage_dtype: str = setting("fp16", choices=STORED_DTYPES, help="dtype the features are stored in (what "
                                 "the model computes in is --compute-dtype)")
    compute_dtype: str = compute_dtype()
    camera_map: str | None = setting(  # native towers: policy camera <- dataset camera where names differ
        None, rule=CAMERA_MAP, codec=codecs.CAMERA_MAP, recipe=False,
        help="native towers: which dataset camera feeds each policy camera where the names differ (checked before "
        "decoding; the cache keeps the dataset's camera names)")
    device: str = setting("cpu", recipe=False, help=DEVICE_HELP)
    batch_size: int = setting(32, rule=POSITIVE)
    num_workers: int = setting(2, rule=WORKERS, help="decode worker processes (0: decode in-process; at most 1024)")
    block_frames: int = setting(256, rule=POSITIVE, help="frames per block file / resumable unit")
    shard: tuple[int, int] | None = setting(  # (i, N): write only shard i of N's blocks (graftcache/extract.py)
        None, rule=SHARD, codec=codecs.SHARD, recipe=False,
        help="write only the i-th of N contiguous ranges of blocks, so that N processes (or machines sharing an "
        "object-store root) extract one cache together; the last to finish marks it complete. Not part of the "
        "cache key; rerun a shard to resume it")
    cache: str | None = setting(None, recipe=False, metavar="DIR|URL", help=CACHE_HELP)
    progress: bool = setting(True, recipe=False, help=PROGRESS_HELP)
    allow_nonfinite: bool = setting(  # cache NaN/inf state/action/features instead of refusing (fit then refuses)
        False, help="cache frames whose state, action or features hold NaN/inf instead of refusing the dataset "
        "(`fit` then refuses the cache unless --drop-nonfinite drops those frames)")
    extra_manifest: dict[str, Any] = setting(default_factory=dict, flag=None, recipe=False)


def _suites() -> tuple[str, ...]:
    return import_string("graftcache.datasets.suites:SUITES")  # imported on use: requests come before datasets


#: A suite a cache can record (graftcache.datasets.suites.SUITES): a typo is refused before any cache is made.
SUITE: Rule = (lambda v: v in _suites(), lambda: f"is not a suite; choose one of {', '.join(_suites())}")
#: Controls besides the plain graft ("none"), which every request runs anyway: each once.
CONTROL_LIST: Rule = (lambda v: len(set(v)) == len(v) and "none" not in v,
                      "must name each control once, and not none (the plain graft always runs)")
#: The fit objectives (graftcache.fit.objectives.OBJECTIVES implements each), as plain data for the CLI.
OBJECTIVES = ("flow", "align", "align-flow")
#: The controls a fit runs besides the plain graft, as plain data for the CLI's help (graftcache.fit.controls.CONTROLS
#: implements each; tests/test_settings.py keeps the two equal); pool-HxW pools the candidate to another grid.
NATIVE_CONTROL = "native"              # the policy's own tower, no graft: the one control evaluated as loaded
NATIVE_GRAFT_CONTROL = "native-graft"  # the policy's own tower through the graft
CONTROLS = (NATIVE_CONTROL, NATIVE_GRAFT_CONTROL, "zero-image", "shuffled-image", "lora")
POOL_PREFIX = "pool-"
DOSE_PREFIX = "noise-"  # noise-A: the candidate's features degraded by dose A in (0, 1) (graftcache/fit/dose.py)
#: Which episodes of each task a fit holds out (graftcache.fit.data.SPLITS implements each; tests/test_settings.py
#: keeps the two equal): graftcache's seeded draw (the default), or lerobot's last ceil(n * eval_fraction).
EVAL_SPLITS = ("graftcache", "lerobot")
#: The recompute plans of a training step, least recompute first (graftcache.backbones.activation_checkpointing.PLANS
#: implements each; tests/test_settings.py keeps the two equal): off keeps every activation of the frozen LM and
#: expert, mlp recomputes each layer's MLP in backward, on each layer whole (activation checkpointing as it was).
RECOMPUTE_PLANS = ("off", "mlp", "on")
#: Whether and how a fit recomputes: a plan, or `auto`, the first plan of RECOMPUTE_PLANS the backbone has whose
#: training step fits the device's memory (graftcache/fit/step_memory.py).
RECOMPUTE_MODES = ("auto", *RECOMPUTE_PLANS)
#: How the frozen LM and expert attend (graftcache/backbones/attention.py): `auto` takes the fused path
#: (scaled_dot_product_attention) where the backbone has one (its spec's `attentions`), else lerobot's own.
ATTENTION_MODES = ("auto", "eager", "sdpa")
#: A results path names a file: "" would be the current folder, and "rdir/" used to write a file named rdir.
RESULTS_FILE: Rule = (lambda v: bool(v.strip()) and not v.endswith(("/", os.sep)),
                      "must name a file, e.g. results.parquet (not empty, not ending in /)")


#: How FitRequest settings enter a cell's identity (graftcache.settings.Identity): for every cell, for cells whose
#: objective takes steps, for the lora control's cells.
ALWAYS, SCHEDULED, LORA = Identity("always"), Identity("scheduled"), Identity("lora")

#: A LoRA rank past the language model's width adds nothing (every backbone's is at most 2048), and each adapter's
#: matrices grow with it: past this the control only allocates.
MAX_LORA_RANK = 4096
LORA_RANK: Rule = (lambda v: 0 < v <= MAX_LORA_RANK, f"must be in 1..{MAX_LORA_RANK} (past every backbone's LM width)")


@dataclass(frozen=True)
class FitRequest(Checked):
    """Everything `graftcache fit` needs: one (backbone, encoder, suite) over seeds and controls."""

    backbone: str = setting(recipe=False, choices=tuple(BACKBONES), cell=ALWAYS, shared=True)
    encoder: str = setting(recipe=False, help="encoder whose cache to graft (registry name)")
    suite: str = setting(recipe=False, rule=SUITE, help=lambda: f"LIBERO suite: {', '.join(_suites()[:-1])}",
                         cell=ALWAYS)
    policy: str = setting("tiny", recipe=False,
                          help="hub id (HF cache), local checkpoint folder, or 'tiny' (the sample-trained tiny "
                          "backbone)")
    dataset: str | None = setting(None, recipe=False, help="dataset the cache must come from (path or hub id)")
    cache_key: str | None = setting(None, recipe=False, help="use this cache (when several match)")
    native_cache_key: str | None = setting(None, recipe=False, help="native tower cache for native controls / align")
    camera_map: str | None = setting(  # "POLICY=CACHE,...": which cache camera feeds each policy camera
        None, rule=CAMERA_MAP, codec=codecs.CAMERA_MAP, recipe=False,
        help="which cache camera feeds each policy camera, e.g. image=agentview,image2=eye_in_hand: needed when the "
        "names differ (cameras are matched by name, never by position); every row records the mapping used "
        "(camera_map)")
    seeds: tuple[int, ...] = setting(
        (0, 1, 2), rule=SEEDS, recipe=False, codec=codecs.SEEDS_COUNT,
        help="how many seeds: N runs seeds 0..N-1 (N >= 1); a comma list or range such as 0,2 or 0-4 names the seeds "
        "instead. For one particular seed use --seed, e.g. --seed 0",
        twin=Twin("--seed", codecs.INTS, "explicit seed list: 0, 0,2, 0-4 or 0-3,7 (exclusive with --seeds)", "LIST"))
    controls: tuple[str, ...] = setting((), rule=CONTROL_LIST, recipe=False, shown="none",
                                        help=f"comma list: {', '.join(CONTROLS)}, {POOL_PREFIX}HxW, {DOSE_PREFIX}A")
    objective: str = setting(
        "flow", choices=OBJECTIVES, recipe=False,
        help="flow: the policy's loss; align: closed-form ridge onto the native tokens (cheap screening)")
    steps: int = setting(300, rule=POSITIVE, cell=SCHEDULED, shared=True, column=True)
    lr: float = setting(1e-3, rule=LEARNING_RATE, help="AdamW's learning rate, in (0, 1]", cell=SCHEDULED, column=True)
    batch_size: int = setting(16, rule=POSITIVE, cell=SCHEDULED, shared=True, column=True)
    buffer_mib: int = setting(  # a column: 0 where the cell trains nothing or by align
        2048, rule=POSITIVE, cell=SCHEDULED, column=True,
        help="MiB of training features held in the shuffle buffer: with --num-workers x 2 prefetched cache blocks, "
        "what bounds the fit's memory whatever the suite's size (more mixes episodes better); reading in this "
        "process (--num-workers 0), up to as much again of read blocks is kept for the next cells")
    eval_fraction: float = setting(0.2, rule=FRACTION, help="held-out share of each task's episodes", cell=ALWAYS,
                                   column=True)
    eval_split_seed: int = setting(0, rule=SEED, cell=ALWAYS, column=True)
    eval_split: str = setting(  # added to cells by results format 4; every earlier cell: graftcache's
        EVAL_SPLITS[0], choices=EVAL_SPLITS, flag="--split", cell=Identity(since=4, before=EVAL_SPLITS[0]),
        column=True,
        help="which --eval-fraction of each task's episodes is held out: graftcache (drawn with --eval-split-seed) or "
        "lerobot (the last ceil(n * fraction), as `lerobot-train --dataset.eval_split` holds out, to compare with "
        "lerobot's validation); rows record it (eval_split)")
    eval_frames: int | None = setting(None, rule=POSITIVE, help="cap on scored held-out frames (evenly spaced)",
                                      cell=ALWAYS, column=True)
    eval_batch_size: int = setting(64, rule=POSITIVE, help="held-out frames denoised at once (memory, not the "
                                   "scores); rows record eval_seconds_per_frame", column=True)
    num_denoise_steps: int | None = setting(None, rule=POSITIVE, cell=ALWAYS, shared=True, column=True)
    lora_rank: int = setting(8, rule=LORA_RANK, help=f"rank of the lora control's adapters (1..{MAX_LORA_RANK})",
                             cell=LORA, column=True)  # the column: the cell's (0 but for the lora control)
    recompute: str = setting(
        "auto", choices=RECOMPUTE_MODES, formerly="activation_checkpointing",
        help="the recompute plan: which activations of the frozen LM and action expert are recomputed during "
        "backward instead of kept (same gradients, less memory, more step time; activation checkpointing): off none, "
        "mlp each layer's MLP, on each layer whole (~1/3 more step time); auto: the first of off, mlp, on the "
        "backbone has whose step fits the device's memory; rows record what it resolved to (column "
        "activation_checkpointing)")
    attention: str = setting(  # in no cell: both paths give the numbers within attention.TOLERANCE
        "auto", choices=ATTENTION_MODES,
        help="how the frozen LM and action expert attend: eager (lerobot's matmul-softmax-matmul, every score matrix "
        "kept) or sdpa (torch's fused scaled_dot_product_attention: same numbers within float rounding, less memory "
        "and time); auto: sdpa where the backbone has it; rows record what it resolved to (attention) and keep "
        "their run_ids")
    compile: bool = setting(  # an execution setting: the numbers agree within float rounding, in no run_id
        False, column=True, shared=True,
        help="torch.compile the frozen backbone's training forward (graftcache/backbones/compiled.py): each training "
        "pass compiles it once, which pays only over enough steps (benchmarks/gpu_check.py measures compile seconds "
        "against step seconds). Rows record it (compile)")
    device: str = setting("cpu", recipe=False, help=DEVICE_HELP)
    num_workers: int = setting(  # the numbers do not depend on it
        2, rule=WORKERS,
        help="processes reading and pooling cached features ahead of the model (0: in this process; at most 1024)")
    cells_per_pass: int | None = setting(  # an execution setting: in no cell, hence in no run_id
        None, rule=POSITIVE, metavar="N", shared=True,
        help="cells (seeds, image controls, encoders of one grid and width) trained together in one forward and "
        "backward of the frozen backbone, each with its own projector, loss, optimiser and random streams; rows equal "
        "one-cell-at-a-time rows up to float rounding and keep their run_ids; lora, align and native cells run alone "
        "(default: per backbone and device, its spec's cells_per_pass: 1 on CPU)")
    compute_dtype: str = compute_dtype(cell=ALWAYS, shared=True, column=True)  # resolved before any cell is named
    results: str = setting("results.parquet", rule=RESULTS_FILE, recipe=False)
    out: str | None = setting(None, help="run folder for projectors (default: runs/ beside --results, or, where that "
                              "cannot be written, runs/ in the local cache folder, as the log says)")
    cache: str | None = setting(None, recipe=False, metavar="DIR|URL", help=CACHE_HELP)
    progress: bool = setting(True, recipe=False, help=PROGRESS_HELP)
    drop_nonfinite: bool = setting(
        False, help="drop frames whose features, state or action chunk hold NaN/inf (a cache holding any is refused "
        "otherwise); the results row records how many (n_dropped_nonfinite)")
    accept_numerics_drift: bool = setting(
        False, help="fit even when this environment computes a cache's features differently from the one that made "
        "it (its numerics fingerprint); each row records the measured drift")
    command: str = setting(default_factory=lambda: " ".join(["graftcache", *sys.argv[1:]]), flag=None, recipe=False,
                           column=True)  # the command line that produced the row


#: Ray's num_gpus: a share of one GPU (several tasks on one device) or whole GPUs.
GPU_SHARE: Rule = (lambda v: v >= 0 and (v <= 1 or float(v).is_integer()), "must be between 0 and 1 or a whole number")


@dataclass(frozen=True)
class ExecutorSettings(Checked):
    """Where `extract`, `sweep` and `rollout` run their work (graftcache/executors/): in this process, or as Ray
    tasks (a rollout's: actors) on a cluster that sees the same cache root and results folder. Nothing here changes
    a number: the caches, run_ids and rows are the same under every executor. All but `executor` apply to the ray
    executor only."""

    executor: str = setting(
        "local", choices=lambda: tuple(import_string("graftcache.executors:EXECUTORS")),
        help="local: this process; ray: Ray tasks (every node must see the dataset, the cache root and the results "
        "folder: a shared file system or an s3:// cache root)")
    address: str | None = setting(None, metavar="ADDR", help="a running Ray cluster to join (auto, ray://HOST:10001); "
                                  "default: start a Ray instance on this machine")
    gpus_per_task: float | None = setting(
        None, rule=GPU_SHARE, metavar="G",
        help="GPUs per task; a fraction shares one GPU between tasks (default: 1 with --device cuda, else 0)")
    cpus_per_task: float = setting(1.0, rule=POSITIVE, metavar="C", help="CPUs per task, also its torch threads")
    shards: int | None = setting(None, rule=POSITIVE, metavar="N",
                                 help="tasks per extraction (default: as many as the cluster runs at once)")
    max_retries: int = setting(3, rule=NON_NEGATIVE, metavar="N",
                               help="reruns of a task whose worker or node died (a task that raised an error is not "
                               "rerun)")


#: train-tiny's frame size: the tiny towers read 128 px at most, and every frame of the dataset is decoded and held at
#: this size (uint8, per camera) for the whole training: past this it only fills memory.
MAX_IMAGE_SIZE = 1024
IMAGE_SIZE: Rule = (lambda v: 0 < v <= MAX_IMAGE_SIZE, f"must be in 1..{MAX_IMAGE_SIZE} (frames held in memory at "
                    "this size)")


@dataclass(frozen=True)
class TinyTrainConfig(Checked):
    """The recipe of `graftcache train-tiny` (it keys the checkpoint folder, with the dataset's identity)."""

    steps: int = setting(300, rule=POSITIVE)  # enough for the tiny backbones to use vision (native beats zero-image)
    batch_size: int = setting(32, rule=POSITIVE)
    lr: float = setting(1e-3, rule=LEARNING_RATE, help="AdamW's learning rate, in (0, 1]")
    weight_decay: float = setting(1e-4, rule=WEIGHT_DECAY, help="AdamW's weight decay, in [0, 1]")
    seed: int = setting(0, rule=SEED)
    image_size: int = setting(
        128, rule=IMAGE_SIZE,
        help=f"frames are resized once to this (>= every tiny tower's input; at most {MAX_IMAGE_SIZE}: every frame of "
        "the dataset is held at this size while training)")
    warmup: float = setting(0.1, rule=(lambda v: 0 <= v < 1, "must be in [0, 1)"),
                            help="share of the steps with a linear warm-up, then cosine decay to 0")
    state_dropout: float = setting(
        0.0, rule=(lambda v: 0 <= v <= 1, "must be in [0, 1]"),
        help="share of training samples whose proprioceptive state reads as the dataset's mean state: a tiny "
        "policy that can always read its state learns to lean on it and barely looks at its cameras")
    compute_dtype: str = compute_dtype()
    cameras: tuple[str, ...] | None = setting(
        None, rule=NAMES, metavar="A,B",
        help="the dataset cameras the policy sees, in this order (default: all of them, in the dataset's order); its "
        "config records their names, so a fit on this dataset matches them by name")

    def as_dict(self, backbone: str) -> dict:
        """The recipe as it keys the checkpoint folder. `cameras` None (the dataset's own) and `state_dropout` 0, the
        only choices before those fields existed, are left out, so checkpoints trained before them are found again
        under their keys."""
        values = asdict(self)
        for name, unset in (("cameras", None), ("state_dropout", 0.0)):  # fields added later: keys stay as they were
            if values[name] == unset:
                del values[name]
        return {"backbone": backbone, **values}


DEFAULT_TINY_TRAIN = TinyTrainConfig()
