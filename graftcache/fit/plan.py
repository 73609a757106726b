"""A fit's Plan: what one FitRequest's cells are, without loading anything.

A `Plan` resolves the request (device, compute dtype, cells per pass, objective, controls), finds the caches it reads
and the policy folder, pairs the cameras and splits the episodes; from these it names every cell
(`graftcache.fit.plan.Cell`: its run_id), says which cells may share a backbone pass (`Plan.pass_key`) and where a
cell's run folder is. The backbone's token grid and a control's feature width are computed here once, from the policy's
config and the cache's layout; the loaded policy's grid is checked against it (`Plan.check_token_grid`). It reads
manifests, indexes and the policy's config only: a finished sweep is skipped from a Plan alone, and the ray executor's
driver makes the Plans whose cells its workers run (graftcache/executors/ray_fit.py).

What a cell then reads is graftcache.fit.materials.Materials; how a pass of cells runs, graftcache.fit.run.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import os
import shutil
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict
from pathlib import Path
from typing import Any

import torch
from safetensors.torch import load_file, save_file

from graftcache import results
from graftcache.backbone_registry import native_name
from graftcache.backbones import get_backbone, registered_spec
from graftcache.backbones.checkpoint import follow_umask
from graftcache.backbones.tiny_record import resolve_policy
from graftcache.cameras import format_camera_map, match_cameras, parse_camera_map, renames
from graftcache.codecs import without_none
from graftcache.errors import FitError
from graftcache.fit.buffer import MIB
from graftcache.fit.controls import Control, check_pool_grid, get_control
from graftcache.fit.data import split_episodes, suite_index_table
from graftcache.fit.lookup import find_cache
from graftcache.fit.objectives import EVAL_ONLY, OBJECTIVES, Objective
from graftcache.fit.stream import FeatureSource
from graftcache.graft import at_width
from graftcache.hashing import sha256_bytes
from graftcache.pooling import format_grid, parse_grid
from graftcache.requests import FitRequest
from graftcache.results.schema import IDENTITY_3_VALUES, make_policy_id
from graftcache.runtime import resolve_compute_dtype, resolve_device
from graftcache.settings import Declared, declared
from graftcache.store import FeatureCache, cache_root
from graftcache.store.readthrough import reading_root

__all__ = ["Cell", "Plan", "Planned"]

PROJECTOR_WEIGHTS = "projector.safetensors"  # in a cell's run folder: its trained parameters
PROJECTOR_SIDECAR = "projector.json"         # beside them: its cell, split and freeze report (graftcache.fit.run)


#: The FitRequest settings each cell holds, as their declarations say (graftcache/requests.py, `cell=`).
CELL_SETTINGS: dict[str, Declared] = {name: d for name, d in declared(FitRequest).items() if d.setting.cell}
#: The FitRequest settings the cells of one backbone pass share (`shared=True`), in declaration order.
PASS_SETTINGS: tuple[str, ...] = tuple(name for name, d in declared(FitRequest).items() if d.setting.shared)


class _CellMethods:
    """What a Cell does (its fields: `Cell`)."""

    @property
    def run_id(self) -> str:
        """Every field, but those added since results.IDENTITY_VERSION where they hold what earlier cells held, and
        the identity's version under the key cells of results format 3 gave it."""
        known = IDENTITY_3_VALUES
        fields = {k: v for k, v in asdict(self).items() if not (k in known and known[k] == v)}
        return results.make_run_id({**fields, "format_version": results.IDENTITY_VERSION})

    @classmethod
    def of_row(cls, row: Mapping[str, Any]) -> Cell:
        """The cell a results row records (every field is a column since results format 5): `row`'s inverse, but for
        `camera_map`, which rows spell out also where every name matched, and cells omit then."""
        fields = {f.name: row[f.name] for f in dataclasses.fields(cls)}
        if fields["camera_map"] is not None and not renames(parse_camera_map(fields["camera_map"])):
            fields["camera_map"] = None
        return cls(**fields)

    def row(self, req: FitRequest, measured: Mapping[str, Any]) -> dict[str, Any]:
        """The results row: each SCHEMA column from what the cell measured, else the cell, else the request
        (so a new column that names a request field needs no code here)."""
        sources = (measured, asdict(self), asdict(req))
        row = {}
        for column in results.SCHEMA:
            source = next((s for s in sources if column in s), None)
            if source is None:
                raise FitError(f"results column {column!r} is neither measured, nor a cell or FitRequest field")
            row[column] = source[column]
        return row


#: What a fit trains and scores, and what identifies its results row: every field, by name and value, is hashed into the
#: row's run_id, with the version of that identity (results.IDENTITY_VERSION); a change of its shape is a new
#: results.FORMAT_VERSION, whose graftcache.results.upgrade says what becomes of older rows. A field added since
#: IDENTITY_VERSION is hashed only where it differs from what every earlier cell held (results.schema.ADDED_TO_CELLS),
#: so that a cell identity version 3 could express keeps its run_id. Every field is a results column. Its fields: what a
#: Plan resolves (the policy as rows name it, the cache read, seed, control, the grid the features are pooled to,
#: resolved so that the run_id hashes what the row writes, the objective as run), then every FitRequest setting declared
#: into cells (CELL_SETTINGS), then the camera map (canonical text, only when a policy camera is fed by another name).
Cell = dataclasses.make_dataclass(
    "Cell",
    [("policy", str), ("cache_key", str), ("seed", int), ("control", str), ("pool_grid", str), ("objective", str),
     *((name, d.hint) for name, d in CELL_SETTINGS.items() if d.setting.cell.since is None),
     ("camera_map", str | None, dataclasses.field(default=None)),
     *((name, d.hint, dataclasses.field(default=d.setting.cell.before))
       for name, d in CELL_SETTINGS.items() if d.setting.cell.since is not None)],
    bases=(_CellMethods,), frozen=True, module=__name__)


def _cell_value(req: FitRequest, name: str, objective: Objective, control: Control) -> Any:
    """A cell's value of a declared setting: the request's where the cell uses it (graftcache.settings.Identity's
    `when`), else its type's zero."""
    d = CELL_SETTINGS[name]
    used = {"always": True, "scheduled": objective.scheduled, "lora": control.lora}[d.setting.cell.when]
    return getattr(req, name) if used else without_none(d.hint)()


class Plan:
    """The cells of one FitRequest, named and grouped without loading anything."""

    def __init__(self, req: FitRequest, log: Callable[[str], None] = print, *, check_device: bool = True) -> None:
        """`check_device` False: a Plan for a device this machine need not have (the ray executor's driver makes
        the Plans of its workers' GPUs; the compute dtype must then be resolved already)."""
        self.device = resolve_device(req.device) if check_device else torch.device(req.device)
        self.req = req = dataclasses.replace(req, compute_dtype=resolve_compute_dtype(req.compute_dtype, self.device))
        spec = registered_spec(req.backbone)  # what the backbone cannot run, refused before anything loads
        if spec is not None:
            spec.check_execution(req.backbone, attention=req.attention, recompute=req.recompute, compile=req.compile)
        self.objective = OBJECTIVES[req.objective]
        self.log = log
        self.root = reading_root(req.cache)  # only read: stage 2 never writes into a cache root
        self.controls = [get_control(c) for c in dict.fromkeys(("none", *req.controls))]
        self.cache = find_cache(self.root, req.encoder, dataset=req.dataset, key=req.cache_key)
        needs_native = self.objective.needs_native or any(c.native_cache for c in self.controls)
        self.native_cache = (find_cache(self.root, native_name(req.backbone), dataset=req.dataset,
                                        key=req.native_cache_key, same_dataset_as=self.cache, for_what="native "
                                        "controls and the align objective") if needs_native else None)
        if self.native_cache is not None:
            strides = {c.manifest.frame_stride for c in (self.cache, self.native_cache)}
            if len(strides) > 1:
                raise FitError(f"caches {self.cache.key} and {self.native_cache.key} hold different frames (frame "
                               f"strides {sorted(strides)}); extract both with the same --frame-stride")
        for control in self.controls:  # a pool control far finer than the stored grid: refused before any load
            source = self.source(control)
            note = check_pool_grid(control, [parse_grid(g) for g in source.manifest.grids], f"cache {source.key}")
            if note:
                log(note)
        self.policy_folder = resolve_policy(req.backbone, req.policy, self.cache.manifest.dataset_identity,
                                            cache_root(req.cache), self.cache.manifest.dataset.source)
        self.cameras = self._match_cameras()
        self.index = suite_index_table(self.cache, req.suite)
        self.split = split_episodes(self.index, eval_fraction=req.eval_fraction, seed=req.eval_split_seed,
                                    rule=req.eval_split)
        self._pass_keys: dict[str, tuple | None] = {}  # control name -> its pass key

    def _match_cameras(self) -> dict[str, str]:
        """Policy camera -> the cache camera feeding it (graftcache/cameras.py: by name unless `camera_map` says
        otherwise), read from the policy's config and checked against every cache the fit reads."""
        policy = get_backbone(self.req.backbone).read_cameras(self.policy_folder)
        mapping: dict[str, str] = {}
        for cache in (self.cache, self.native_cache):
            if cache is not None:
                mapping = match_cameras(policy, cache.manifest.cameras, self.req.camera_map,
                                        policy_name=str(self.policy_folder), cache_name=f"cache {cache.key}")
        if renames(mapping):
            self.log(f"cameras mapped as asked (policy=cache): {format_camera_map(mapping)}")
        return mapping

    # ---------------------------------------------------------------- what a cell reads and how it is fitted
    def source(self, control: Control) -> FeatureCache:
        """The cache a control reads: the native tower's for the native controls, else the encoder's."""
        return self.native_cache if control.native_cache else self.cache

    def objective_of(self, control: Control) -> Objective:
        """How a control's cells are fitted: the request's objective, or nothing for controls that train nothing."""
        return self.objective if control.train else EVAL_ONLY

    @functools.cached_property
    def token_grid(self) -> tuple[int, int]:
        """The backbone's per-camera token grid, read from the policy's config (nothing is loaded): the one its cells
        hash and are fed; the loaded policy's is checked against it (`check_token_grid`)."""
        return get_backbone(self.req.backbone).read_token_grid(self.policy_folder)

    def check_token_grid(self, loaded: tuple[int, int]) -> None:
        """Refuse a loaded policy whose token grid is not the one its config gave the cells' run_ids."""
        if tuple(loaded) != tuple(self.token_grid):
            raise FitError(f"backbone {self.req.backbone}: the policy loaded from {self.policy_folder} takes a "
                           f"{format_grid(loaded)} token grid, its config says {format_grid(self.token_grid)}; fix "
                           f"the adapter's read_token_grid so that both agree")

    def grid(self, control: Control) -> tuple[int, int]:
        """The grid a control's cells pool the features to: its own, else the backbone's."""
        return control.grid or self.token_grid

    def width(self, control: Control) -> int:
        """The feature width a control's projector takes, from the cache's layout (nothing is read)."""
        source = FeatureSource.of(self.source(control), list(self.cameras.values()), self.grid(control), control.extra)
        return source.frame_shape(source.cameras[0])[1]

    @property
    def policy_name(self) -> str:
        """How rows name the policy: as given, or `tiny:<folder>` for the tiny policy trained on this dataset."""
        return self.req.policy if self.req.policy != "tiny" else f"tiny:{Path(self.policy_folder).name}"

    # ---------------------------------------------------------------- cells
    def cell(self, control: Control, seed: int) -> Cell:
        """What identifies a results row (hashed into its run_id); computable without loading anything."""
        objective = self.objective_of(control)
        return Cell(
            policy=self.policy_name, cache_key=self.source(control).key, seed=seed, control=control.name,
            pool_grid=format_grid(self.grid(control)), objective=objective.name,
            camera_map=format_camera_map(self.cameras) if renames(self.cameras) else None,
            **{name: _cell_value(self.req, name, objective, control) for name in CELL_SETTINGS},
        )

    def policy_id(self, cell: Cell) -> str:
        """What decides the function of the cell's policy and its scores (results.schema.make_policy_id): the cell's
        fields, less those its control's policy ignores (graftcache.fit.controls.Control.ignores), each replaced by
        what stands in for it (STAND_INS; a field with no stand-in is simply left out)."""
        control = self.control(cell)
        fields = {k: v for k, v in asdict(cell).items() if k not in control.ignores}
        stand_ins = {STAND_INS[name][0]: STAND_INS[name][1](self, control) for name in control.ignores
                     if name in STAND_INS}
        return make_policy_id({**fields, **stand_ins})

    def frames(self, control: Control) -> dict[str, Any]:
        """What decides which frames a control's cells train and are scored on, in which draws, when its features
        decide nothing (zero-image): the dataset's content, which of its frames the cache holds at which rows (the
        suite's index), the cache's block layout (blocks are drawn whole), the shuffle buffer's frames where its MiB
        hold fewer than the training split (a width's frame bytes then decide them), the native cache align fits
        to, and the cache's key itself where frames with NaN/inf features are dropped (which ones: its features')."""
        cache = self.source(control)
        suite = self.index if cache is self.cache else suite_index_table(cache, self.req.suite)
        index = suite.select("row", "index").to_numpy().astype("int64")
        out: dict[str, Any] = {"dataset": cache.manifest.dataset_identity, "frames": sha256_bytes(index.tobytes()),
                               "block_frames": int(cache.layout["block_frames"])}
        objective = self.objective_of(control)
        if objective.scheduled:
            source = FeatureSource.of(cache, list(self.cameras.values()), self.grid(control), control.extra)
            held = self.req.buffer_mib * MIB // max(source.frame_bytes(), 1)
            train = int(suite["episode_index"].is_in(list(self.split.train_episodes)).sum())
            out["buffer_frames"] = held if held < train else None
        if objective.needs_native:
            out["targets"] = self.native_cache.key
        if self.req.drop_nonfinite:
            out["features"] = cache.key
        return out

    def cells(self) -> list[Cell]:
        """Every cell of the request (each seed, each control), in the order a fit visits them."""
        return [self.cell(control, seed) for seed in self.req.seeds for control in self.controls]

    def control(self, cell: Cell) -> Control:
        """The control a cell of this plan runs."""
        return next(c for c in self.controls if c.name == cell.control)

    def pass_key(self, control: Control) -> tuple | None:
        """What cells must share to train in one pass of the backbone (graftcache/fit/passes.py): the loaded
        policy on its device, the shape of the tokens fed to it (grid and width), and every setting declared shared
        (PASS_SETTINGS: the backbone, compute dtype, training schedule, the scoring's denoising, `cells_per_pass`,
        None there meaning the backbone's default on the key's device). None: the cell runs alone (LoRA, align,
        controls that train nothing). Read from the policy's config and the cache's layout: nothing is loaded."""
        if control.name not in self._pass_keys:
            key = None
            adapter = get_backbone(self.req.backbone)
            if control.fuses and self.objective_of(control).fuses and adapter.spec.loss_per_sample:
                key = (str(self.policy_folder), str(self.device), self.grid(control), self.width(control),
                       *(getattr(self.req, name) for name in PASS_SETTINGS))
            self._pass_keys[control.name] = key
        return self._pass_keys[control.name]

    def skipped(self, cells: Sequence[Cell]) -> None:
        """Say in one line which of this request's cells are skipped, their rows being in the results file already:
        by control (with the tower a native control reads), the seeds of each."""
        seeds: dict[str, list[str]] = {}
        for cell in cells:
            source = self.source(self.control(cell)).manifest.encoder_name
            name = cell.control if source == self.req.encoder else f"{cell.control} ({source})"
            seeds.setdefault(name, []).append(str(cell.seed))
        which = "; ".join(f"{name}: seed{'s' * (len(s) > 1)} {', '.join(s)}" for name, s in seeds.items())
        self.log(f"skip {self.req.backbone}/{self.req.encoder}/{self.req.suite}: {len(cells)} "
                 f"cell{'s' * (len(cells) > 1)} already in {self.req.results} (control {which})")

    # ---------------------------------------------------------------- a cell of a policy already scored
    def copied_row(self, cell: Cell, original: Mapping[str, Any]) -> dict[str, Any]:
        """The row of `cell` made from the row of another run of the same policy (`policy_id`), scored on the same
        frames: the original's scores and measurements, with what is the cell's own (its fields and run_id, its
        encoder, cache and camera map, its command; numerics_drift null: its cache's features were never read;
        wall_s 0: nothing was fitted for it)."""
        source = self.source(self.control(cell)).manifest
        own = {**asdict(cell), "run_id": cell.run_id, "format_version": results.FORMAT_VERSION,
               "encoder": source.encoder_name, "command": self.req.command,
               "encoder_random_init": source.unreleased,
               "random_init": source.unreleased or bool(original["backbone_random_init"]), "numerics_drift": None,
               "camera_map": format_camera_map(self.cameras), "wall_s": 0.0}
        return {column: own[column] if column in own else original[column] for column in results.SCHEMA}

    def copy_run_folder(self, cell: Cell, original: Path) -> bool:
        """Give `cell` the projector of the run folder `original` (an export reads it by run_id), its sidecar naming
        this cell and the run it was copied from; False where that folder holds no projector. A projector of another
        feature width (a zero-image run of another cache) is rebuilt at the cell's (graftcache.graft.at_width), so
        that the export grafts it as it grafts the cell's own."""
        if not (original / PROJECTOR_WEIGHTS).is_file():
            return False
        folder = self.run_folder(cell)
        folder.mkdir(parents=True, exist_ok=True)
        control = self.control(cell)
        saved = load_file(str(original / PROJECTOR_WEIGHTS))
        try:
            widened = at_width(saved, control.projector, self.width(control))
        except ValueError as e:
            raise FitError(f"{original / PROJECTOR_WEIGHTS}: cannot be run {cell.run_id}'s projector: {e}") from None
        partial = folder / f".{PROJECTOR_WEIGHTS}.partial-{os.getpid()}"
        if widened is saved:
            shutil.copyfile(original / PROJECTOR_WEIGHTS, partial)
        else:
            save_file(widened, str(partial))
        follow_umask(partial)
        os.replace(partial, folder / PROJECTOR_WEIGHTS)
        recorded = original / PROJECTOR_SIDECAR
        sidecar = json.loads(recorded.read_text()) if recorded.is_file() else {}
        sidecar.update(run_id=cell.run_id, cell=asdict(cell), copied_from=original.name)
        (folder / PROJECTOR_SIDECAR).write_text(json.dumps(sidecar, indent=2, default=str))
        return True

    # ---------------------------------------------------------------- where a cell's files go
    def run_folder(self, cell: Cell) -> Path:
        """Where a cell's projector (and a row its results file could not take) is kept."""
        return self.runs / cell.run_id

    @functools.cached_property
    def runs(self) -> Path:
        """The folder of the run folders: --out, else runs/ beside the results file; where that cannot be written
        (a read-only results folder), runs/ in the local cache folder (store.cache_root), said in the log: the
        projector save would fail first and lose the cell's work, its row then being kept there too."""
        if self.req.out:
            return Path(self.req.out)
        beside = Path(self.req.results).absolute().parent / "runs"
        existing = next(p for p in (beside, *beside.parents) if p.exists())  # what creating it writes into
        if os.access(existing, os.W_OK | os.X_OK):  # False on a read-only mount, also for root
            return beside
        runs = cache_root(self.req.cache) / "runs"
        self.log(f"cannot write run folders beside {self.req.results} ({existing} is not writable): projectors, and "
                 f"rows the results file cannot take, are kept in {runs} (--out names another folder)")
        return runs


#: A cell field some control's policy ignores -> (the key its policy_id hashes instead, what stands in for it): the
#: encoder's cache of zero-image cells, whose features are zeroed, by what decides their frames.
STAND_INS: dict[str, tuple[str, Callable[[Plan, Control], Any]]] = {"cache_key": ("frames", Plan.frames)}


#: A cell as a pass holds it: with the Plan of its request (what it reads, where its row and run folder go).
Planned = tuple[Plan, Cell]
