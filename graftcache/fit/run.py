"""Stage 2 orchestration: caches -> cells (seed x control) -> one results row per cell.

A cell is fitted against the frozen policy, loaded once per run and reset to its pristine state
between cells (graft surgery mutates it), from cached features only. Finished cells (same run_id in
the results file) are skipped before anything is loaded, so reruns and sweeps resume where they
stopped and a finished grid only reads. The projector of every trained cell is saved as safetensors with a JSON
sidecar in the run folder.
"""

from __future__ import annotations

import dataclasses
import json
import sys
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import torch
from safetensors.torch import save_file

import graftcache
from graftcache import results
from graftcache.backbones.checkpoint import follow_umask
from graftcache.backbones.pool import BackbonePool
from graftcache.checks import FRACTION, NON_NEGATIVE, POSITIVE, SEEDS, Checked, Rule
from graftcache.errors import FitError
from graftcache.fit.align import fit_ridge
from graftcache.fit.controls import Control, get_control, transform_features
from graftcache.fit.data import FrameTable, Split, load_frames, split_episodes, suite_index_table
from graftcache.fit.loop import TrainConfig, camera_map, evaluate, train
from graftcache.fit.lookup import find_cache, native_encoder_name, resolve_policy
from graftcache.graft import GraftProjector, IdentityProjector
from graftcache.pooling import format_grid
from graftcache.runtime import resolve_compute_dtype, resolve_device, resolve_dtype, set_main_threads
from graftcache.store import FeatureCache, cache_root
from graftcache.store.readthrough import reading_root

OBJECTIVES = ("flow", "align")


@dataclass(frozen=True)
class FitRequest(Checked):
    backbone: str
    encoder: str
    suite: str
    policy: str = "tiny"
    dataset: str | None = None
    cache_key: str | None = None
    native_cache_key: str | None = None
    seeds: tuple[int, ...] = (0, 1, 2)
    controls: tuple[str, ...] = ()
    objective: str = "flow"
    steps: int = 300
    lr: float = 1e-3
    batch_size: int = 16
    eval_fraction: float = 0.2
    eval_split_seed: int = 0
    eval_frames: int | None = None
    num_denoise_steps: int | None = None
    lora_rank: int = 8
    device: str = "cpu"
    compute_dtype: str = "auto"  # resolved per device (runtime.resolve_compute_dtype) before it reaches a row
    results: str = "results.parquet"
    out: str | None = None
    cache: str | None = None
    progress: bool = True
    command: str = field(default_factory=lambda: " ".join(["graftcache", *sys.argv[1:]]))

    RULES: ClassVar[dict[str, Rule]] = {
        "seeds": SEEDS, "steps": POSITIVE, "lr": POSITIVE, "batch_size": POSITIVE, "eval_fraction": FRACTION,
        "eval_split_seed": NON_NEGATIVE, "eval_frames": POSITIVE, "num_denoise_steps": POSITIVE, "lora_rank": POSITIVE,
    }


@dataclass
class _Material:
    """What one (request, control) needs: split tables of features + the encoder identity."""

    train: FrameTable
    eval: FrameTable
    cache: FeatureCache
    encoder: str
    grid: tuple[int, int] | None
    targets: tuple[FrameTable, FrameTable] | None = None  # native tokens, for `align`


def _evaluate_subset(table: FrameTable, max_frames: int | None) -> FrameTable:
    """At most `max_frames` evenly spaced eval frames (deterministic), whole table otherwise."""
    if max_frames is None or len(table) <= max_frames:
        return table
    keep = np.linspace(0, len(table) - 1, max_frames).round().astype(int)
    t = torch.from_numpy(keep)
    return FrameTable(table.rows[keep], table.episode_index[keep], {c: f[t] for c, f in table.features.items()},
                      table.state[t], table.actions[t], table.action_pad[t], table.task_index[t], table.tasks)


def _split(table: FrameTable, split: Split) -> tuple[FrameTable, FrameTable]:
    return table.subset(split.train_episodes), table.subset(split.eval_episodes)


class Fitter:
    """Runs every cell of a FitRequest; `run()` returns the rows it wrote."""

    def __init__(self, req: FitRequest, log: Callable[[str], None] = print,
                 backbones: BackbonePool | None = None) -> None:
        if req.objective not in OBJECTIVES:
            raise FitError(f"--objective {req.objective!r}: choose one of {', '.join(OBJECTIVES)}")
        self.device = resolve_device(req.device)
        self.req = req = dataclasses.replace(req, compute_dtype=resolve_compute_dtype(req.compute_dtype, self.device))
        self.log = log
        self.backbones = backbones or BackbonePool(log)
        self.root = reading_root(req.cache)  # only read: stage 2 never writes into a cache root
        self.dtype = resolve_dtype(req.compute_dtype)
        self.controls = [get_control(c) for c in dict.fromkeys(("none", *req.controls))]
        self.cache = find_cache(self.root, req.encoder, dataset=req.dataset, key=req.cache_key)
        needs_native = req.objective == "align" or any(c.uses_native_cache for c in self.controls)
        self.native_cache = (find_cache(self.root, native_encoder_name(req.backbone), dataset=req.dataset,
                                        key=req.native_cache_key, same_dataset_as=self.cache, for_what="native "
                                        "controls and the align objective") if needs_native else None)
        if self.native_cache is not None:
            strides = {c.manifest.get("frame_stride") or 1 for c in (self.cache, self.native_cache)}
            if len(strides) > 1:
                raise FitError(f"caches {self.cache.key} and {self.native_cache.key} hold different frames (frame "
                               f"strides {sorted(strides)}); extract both with the same --frame-stride")
        self.policy_folder = resolve_policy(req.backbone, req.policy, self.cache.manifest["dataset_fingerprint"],
                                            cache_root(req.cache), self.cache.manifest["dataset"]["source"])
        self.index = suite_index_table(self.cache, req.suite)
        self.split = split_episodes(self.index, eval_fraction=req.eval_fraction, seed=req.eval_split_seed)
        self.train_cfg = TrainConfig(steps=req.steps, lr=req.lr, batch_size=req.batch_size,
                                     num_denoise_steps=req.num_denoise_steps, dtype=self.dtype,
                                     progress=req.progress)
        self._materials: dict[tuple, _Material] = {}

    # ---------------------------------------------------------------- loading
    def _source(self, control: Control) -> FeatureCache:
        """The cache a control reads: the native tower's for the native controls, else the encoder's."""
        return self.native_cache if control.uses_native_cache else self.cache

    def _adapter(self):
        return self.backbones.get(self.req.backbone, self.policy_folder, str(self.device))

    def _material(self, adapter, control: Control) -> _Material:
        grid = control.grid or adapter.native_grid
        source = self._source(control)
        extra = "connector" if control.features == "native-tokens" else None
        key = (source.key, extra, None if extra else grid)
        if key not in self._materials:
            cams = list(camera_map(adapter, source.manifest["cameras"]).values())
            table = load_frames(source, self.req.suite, cameras=cams, grid=None if extra else grid,
                                chunk=adapter.chunk_size, extra=extra)
            tr, ev = _split(table, self.split)
            encoder = source.manifest["encoder"]["name"]
            mat = _Material(tr, _evaluate_subset(ev, self.req.eval_frames), source, encoder, grid)
            if self.req.objective == "align" and control.projector == "graft":
                native = load_frames(self.native_cache, self.req.suite, cameras=cams, grid=None,
                                     chunk=adapter.chunk_size, extra="connector")
                mat.targets = _split(native, self.split)
            self._materials[key] = mat
        return self._materials[key]

    # ---------------------------------------------------------------- cells
    def cell(self, control: Control, seed: int, policy_id: str) -> dict[str, Any]:
        """What identifies a results row (hashed into its run_id); computable without loading anything."""
        objective = "eval" if not control.train else self.req.objective
        trained = control.train
        source = self._source(control)
        return {
            "backbone": self.req.backbone, "policy": policy_id, "cache_key": source.key,
            "suite": self.req.suite, "seed": seed, "control": control.name,
            "pool_grid": format_grid(control.grid) if control.grid else "native", "objective": objective,
            "steps": self.req.steps if trained and objective == "flow" else 0,
            "lr": self.req.lr if trained and objective == "flow" else 0.0,
            "batch_size": self.req.batch_size if trained and objective == "flow" else 0,
            "lora_rank": self.req.lora_rank if control.lora else 0,
            "eval_fraction": self.req.eval_fraction, "eval_split_seed": self.req.eval_split_seed,
            "eval_frames": self.req.eval_frames, "num_denoise_steps": self.req.num_denoise_steps,
            "compute_dtype": self.req.compute_dtype,
        }

    def run(self) -> list[dict[str, Any]]:
        set_main_threads()
        done = results.done_run_ids(self.req.results)
        rows = []
        policy_id = self.req.policy if self.req.policy != "tiny" else f"tiny:{Path(self.policy_folder).name}"
        for seed in self.req.seeds:
            for control in self.controls:
                cell = self.cell(control, seed, policy_id)
                run_id = results.make_run_id(cell)
                if run_id in done:
                    encoder = self._source(control).manifest["encoder"]
                    self.log(f"skip {self.req.backbone}/{encoder['name']}/{self.req.suite} seed {seed} "
                             f"control {control.name}: already in {self.req.results}")
                    continue
                adapter = self._adapter()
                mat = self._material(adapter, control)
                row = self._run_cell(adapter, control, seed, mat, cell, run_id)
                results.append(self.req.results, [row])
                rows.append(row)
                self.log(f"{row['backbone']}/{row['encoder']}/{row['suite']} seed {seed} control {control.name}: "
                         f"eval_mse {row['eval_mse']:.4f} (first {row['eval_mse_first']:.4f}, raw "
                         f"{row['eval_mse_raw']:.5f}) on {row['n_eval_frames']} frames, {row['wall_s']:.1f}s")
        return rows

    def _run_cell(self, adapter, control: Control, seed: int, mat: _Material, cell: dict, run_id: str) -> dict:
        t0 = time.perf_counter()
        torch.manual_seed(seed)
        width = next(iter(mat.train.features.values())).shape[-1]
        projector = (IdentityProjector(adapter.lm_width) if control.projector == "identity"
                     else GraftProjector(width, adapter.lm_width))
        if control.projector == "identity" and width != adapter.lm_width:
            raise FitError(f"native cache {mat.cache.key}: connector tokens are {width} wide, "
                           f"{self.req.backbone} expects {adapter.lm_width}")
        adapter.graft(projector)
        if control.lora:
            adapter.add_lora(rank=self.req.lora_rank)
        self.log(f"cell {run_id}: {adapter.freeze_report()}")
        cams = camera_map(adapter, [c for c in mat.train.features])
        train_feats = transform_features(mat.train.features, control, seed)
        eval_feats = transform_features(mat.eval.features, control, seed + 1)
        loss = float("nan")
        if control.train and cell["objective"] == "flow":
            loss = train(adapter, mat.train, cams, self.train_cfg, seed, features=train_feats, log=self.log)
        elif control.train:  # align
            tr_targets = [mat.targets[0].features[c] for c in cams.values()]
            r2 = fit_ridge(projector, [train_feats[c] for c in cams.values()], tr_targets, mat.grid)
            loss = 1.0 - r2
        score = evaluate(adapter, mat.eval, cams, self.train_cfg, features=eval_feats)
        wall = time.perf_counter() - t0
        self._save_projector(adapter, run_id, cell, control)
        encoder = mat.encoder
        return {
            "run_id": run_id, "backbone": self.req.backbone, "policy": cell["policy"],
            "policy_sha256": adapter.policy_sha256, "encoder": encoder, "cache_key": mat.cache.key,
            "suite": self.req.suite, "seed": seed, "control": control.name, "pool_grid": format_grid(mat.grid),
            "objective": cell["objective"], "steps": cell["steps"], "lr": cell["lr"],
            "batch_size": cell["batch_size"], "train_loss_final": loss, "eval_mse": score.mse,
            "eval_mse_first": score.mse_first, "eval_mse_raw": score.mse_raw,
            "eval_mse_episodes": [score.per_episode[e] for e in sorted(score.per_episode)],
            "n_eval_frames": score.n_frames,
            "n_eval_episodes": len(score.per_episode), "eval_split_seed": self.req.eval_split_seed,
            "wall_s": wall, "device": str(self.device), "compute_dtype": self.req.compute_dtype,
            "random_init": bool(mat.cache.manifest.get("random_init") or adapter.random_init),
            "graftcache_version": graftcache.__version__, "command": self.req.command,
        }

    def _save_projector(self, adapter, run_id: str, cell: dict, control: Control) -> None:
        if control.projector == "identity":
            return
        out = Path(self.req.out) if self.req.out else Path(self.req.results).parent / "runs"
        folder = out / run_id
        folder.mkdir(parents=True, exist_ok=True)
        trainable = {n: p.detach().cpu().contiguous() for n, p in adapter.policy.named_parameters() if p.requires_grad}
        save_file(trainable, str(folder / "projector.safetensors"))
        follow_umask(folder / "projector.safetensors")
        sidecar = {"run_id": run_id, "cell": cell, "split": asdict(self.split),
                   "freeze": str(adapter.freeze_report()), "graftcache_version": graftcache.__version__}
        (folder / "projector.json").write_text(json.dumps(sidecar, indent=2, default=str))
