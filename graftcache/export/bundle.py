"""`graftcache export`: a results row's cell -> a folder lerobot loads as a policy of type `graftcache`.

The folder is written beside its destination, in a folder of its own process's (so two exports of one cell at once
never write into one folder), and renamed into place only once the policy it describes has been built from it (the
numerics fingerprint recomputed, the projector loaded into the grafted base), so a folder at `out` is always a
complete export; the first of two concurrent exports to finish places its folder, the other finds it there. `out`
must be absent or empty: a folder holding anything else is refused, never emptied. An export records no path of its
own (its preprocessor carries the cell's cameras, graftcache.export.processors), so it runs wherever it is moved or
copied; it names the base policy and the cache manifest of the encoder it needs.
"""

from __future__ import annotations

import dataclasses
import errno
import json
import os
import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

from graftcache.cameras import parse_camera_map
from graftcache.errors import ExportError, GraftcacheError
from graftcache.export.locate import check_cache_root, find_row
from graftcache.fit.controls import get_control
from graftcache.fit.dose import SPREAD_FILE
from graftcache.fit.lookup import find_cache
from graftcache.fit.run import PROJECTOR_SIDECAR, PROJECTOR_WEIGHTS, Cell, saved_cell, saved_policy_folder
from graftcache.requests import FitRequest
from graftcache.settings import declared, default_of
from graftcache.store import cache_root
from graftcache.store.readthrough import reading_root

POLICY_PREFIX = "tiny:"  # how rows name a policy trained by train-tiny (graftcache.fit.plan.Plan.policy_name)


def cell_of(row: dict[str, Any], folder: Path | None) -> Cell:
    """The row's Cell, checked to hash to the row's run_id: the row records it whole (results format 5). A row
    upgraded from an older format lacks some of its fields (null); its cell is then the one its fit kept beside its
    projector (`folder`/projector.json) where it trained one, else (a cell that trained nothing has no run folder)
    the row's with each unrecorded field at its FitRequest default, where that hashes to the row's run_id."""
    cell = Cell.of_row(row)
    if cell.run_id == row["run_id"]:
        return cell
    recorded = saved_cell(folder) if folder is not None else None
    if recorded is not None:
        return _checked(row, recorded, f"its run folder's {PROJECTOR_SIDECAR}")
    unrecorded = [f.name for f in dataclasses.fields(Cell) if row[f.name] is None and f.name in declared(FitRequest)]
    defaults = dataclasses.replace(cell, **{name: default_of(FitRequest, name) for name in unrecorded})
    if defaults.run_id == row["run_id"]:
        return defaults
    raise ExportError(f"run {row['run_id']}: its row does not record its whole cell (a row of results format < 5: "
                      f"{', '.join(unrecorded) or 'no field'} unrecorded, not at their defaults) and it has no run "
                      "folder that does; rerun its fit into another --results with this graftcache to export it")


def _checked(row: dict[str, Any], cell: Cell, source: str) -> Cell:
    if cell.run_id != row["run_id"]:
        raise ExportError(f"run {row['run_id']}: {source} gives another cell ({cell.run_id}); the row cannot be "
                          "exported faithfully")
    return cell


def base_policy(row: dict[str, Any], cache: str | None, folder: Path | None = None) -> str:
    """The row's policy as lerobot-loadable source: train-tiny's folder for `tiny:<name>`; else the absolute folder
    the fit loaded, as its run `folder` recorded it (the row names the policy as given, perhaps relative to the
    folder the fit ran in); else as the row says, a folder resolved from here."""
    policy = row["policy"]
    recorded = saved_policy_folder(folder) if folder is not None else None
    if recorded is not None and not policy.startswith(POLICY_PREFIX):
        if not Path(recorded).is_dir():
            raise ExportError(f"run {row['run_id']}: its policy folder {recorded} (its fit's --policy {policy}) is "
                              "gone; restore it there")
        return recorded
    if policy.startswith(POLICY_PREFIX):
        folder = cache_root(cache) / "policies" / policy.removeprefix(POLICY_PREFIX)
        if not (folder / "config.json").is_file():
            raise ExportError(f"run {row['run_id']}: its policy {policy} is not in {folder.parent} (pass the --cache "
                              f"its fit used)")
        return str(folder.resolve())
    if Path(policy).is_dir():
        return str(Path(policy).resolve())
    if policy.startswith((".", "/")):
        raise ExportError(f"run {row['run_id']}: its policy folder {policy} is not there from {Path.cwd()} and no "
                          "run folder records where its fit found it; run export from the folder the fit ran in")
    return policy


def run_folder(row: dict[str, Any], results_path: str | Path, cache: str | None, runs: str | None) -> Path:
    """Where the cell's fit kept its projector (graftcache.fit.plan.Plan.runs: --out, beside the results file, or
    the local cache folder)."""
    places = [Path(runs)] if runs else [Path(results_path).absolute().parent / "runs", cache_root(cache) / "runs"]
    for place in places:
        if (place / row["run_id"] / PROJECTOR_WEIGHTS).is_file():
            return place / row["run_id"]
    raise ExportError(f"run {row['run_id']}: no {PROJECTOR_WEIGHTS} in {' or '.join(str(p) for p in places)} "
                      f"(pass --runs, the folder its fit's --out named)")


def export_run(run_id: str, results_path: str | Path, out: str | Path, *, cache: str | None = None,
               runs: str | None = None, reuse: bool = False, log: Callable[[str], None] = print) -> Path:
    """Write the export of cell `run_id` of `results_path` to `out`; returns `out`. `reuse`: a complete export of
    the run already at `out` (another process's, say) is returned as it is instead of refused."""
    from graftcache.backbones import get_backbone
    from graftcache.export.configuration_graftcache import EXPORT_FORMAT, GraftcacheConfig
    from graftcache.export.features import MANIFEST_FILE
    from graftcache.export.modeling_graftcache import PROJECTOR_FILE, GraftcachePolicy
    from graftcache.export.processors import export_pipelines

    row = find_row(results_path, run_id)
    check_cache_root(row, cache)
    control = get_control(row["control"])
    folder = run_folder(row, results_path, cache, runs) if control.train else None
    if control.dose is not None and not (folder / SPREAD_FILE).is_file():
        raise ExportError(f"run {run_id}: {folder / SPREAD_FILE} is missing (the feature spread its dose noise was "
                          "scaled by); fit the cell again to export it")
    cell = cell_of(row, folder)
    if not control.closed_loop:
        raise ExportError(f"run {run_id}: control {control.name} has no closed-loop meaning (it feeds features of "
                          f"other frames); export another control")
    out = Path(out).absolute()
    if export_of(out) == run_id:
        if reuse:
            return out
        raise ExportError(f"{out}: already holds the export of run {run_id}; remove it or choose another --out")
    check_destination(out)
    policy = base_policy(row, cache, folder)
    feature_cache = find_cache(reading_root(cache), row["encoder"], key=row["cache_key"])
    adapter_cls = get_backbone(row["backbone"])
    base = adapter_cls.load(policy, device="cpu")
    cameras = parse_camera_map(row["camera_map"])
    image_features = {f"observation.images.{cameras[c]}": base.config.image_features[f"observation.images.{c}"]
                      for c in base.cameras}
    config = GraftcacheConfig(
        run_id=run_id, backbone=row["backbone"], base_policy=policy, cache_key=row["cache_key"],
        encoder=row["encoder"], control=control.name, pool_grid=row["pool_grid"], cameras=cameras,
        lora_rank=cell.lora_rank, num_denoise_steps=cell.num_denoise_steps,
        compute_dtype=row["compute_dtype"], n_action_steps=int(getattr(base.config, "n_action_steps", 1)),
        export_format=EXPORT_FORMAT, dose=control.dose, dose_seed=None if control.dose is None else int(row["seed"]),
        input_features={**image_features, "observation.state": base.config.input_features["observation.state"]},
        output_features=dict(base.config.output_features), device="cpu")
    del base
    out.parent.mkdir(parents=True, exist_ok=True)
    try:
        partial = Path(tempfile.mkdtemp(prefix=f".{out.name}.partial-", dir=out.parent))
    except OSError as e:  # named by the folder the user chose, not by the temporary name it could not make
        raise OSError(e.errno, e.strerror, str(out.parent)) from None
    try:
        config.save_pretrained(partial)
        (partial / MANIFEST_FILE).write_text(json.dumps({"key": feature_cache.key,
                                                          "manifest": feature_cache.manifest.to_dict()}, default=str))
        if control.train:
            shutil.copyfile(folder / PROJECTOR_WEIGHTS, partial / PROJECTOR_FILE)
        if control.dose is not None:
            shutil.copyfile(folder / SPREAD_FILE, partial / SPREAD_FILE)
        for pipeline in export_pipelines(run_id, cameras, row["backbone"], policy):
            pipeline.save_pretrained(partial)
        check_processors(partial)
        GraftcachePolicy(config, partial)  # refuses numerics drift and a projector that does not fit, here
        placed = place(partial, out, run_id)
    except OSError as e:
        if e.errno not in (errno.ENOSPC, errno.EDQUOT):
            raise
        # a copy names its source; the space that ran out is the destination's
        raise OSError(e.errno, e.strerror, str(out.parent)) from None
    finally:
        shutil.rmtree(partial, ignore_errors=True)
    log(f"exported {row['backbone']}/{row['encoder']}/{row['suite']} seed {row['seed']} control {control.name} "
        f"(run {run_id}) to {out}" + ("" if placed else " (another process placed the same export there first)"))
    return out


def required_files(config: dict[str, Any]) -> list[str]:
    """The files a complete export of `config` (its config.json, read) holds (the projector only where its control
    trains one, the feature spread only for a dose cell)."""
    from graftcache.backbones.checkpoint import POSTPROCESSOR_FILE, PREPROCESSOR_FILE
    from graftcache.export.features import MANIFEST_FILE
    from graftcache.export.modeling_graftcache import PROJECTOR_FILE

    control = get_control(config.get("control", "none"))
    return ["config.json", MANIFEST_FILE, PREPROCESSOR_FILE, POSTPROCESSOR_FILE,
            *([PROJECTOR_FILE] if control.train else []), *([SPREAD_FILE] if control.dose is not None else [])]


def export_of(folder: Path) -> str | None:
    """The run_id of the complete export at `folder`, None where there is none (nothing there, another kind of
    folder, an export of another format, or one missing one of its files, which only an older graftcache or a hand
    could leave)."""
    from graftcache.export.configuration_graftcache import EXPORT_FORMAT

    try:
        config = json.loads((folder / "config.json").read_text())
        complete = (config.get("type") == "graftcache" and config.get("export_format") == EXPORT_FORMAT
                    and all((folder / f).is_file() for f in required_files(config)))
    except (OSError, ValueError, GraftcacheError):
        return None
    return config.get("run_id") if complete else None


def check_destination(out: Path) -> None:
    """Refuse, in one line and before any work, an `out` that is not a folder to write: a file, or a folder that
    holds anything (an export's files included: never emptied for the user)."""
    if out.exists() and not out.is_dir():
        raise ExportError(f"{out}: is a file, not a folder; choose another --out")
    held = sorted(p.name for p in out.iterdir()) if out.is_dir() else []
    if held:
        what = "an incomplete or other export" if "config.json" in held else "files that are not an export"
        shown = ", ".join(held[:3]) + (f" and {len(held) - 3} more" if len(held) > 3 else "")
        raise ExportError(f"{out}: holds {what} ({shown}); nothing was written: remove it or choose another --out")


def place(partial: Path, out: Path, run_id: str) -> bool:
    """Rename the finished `partial` to `out`; False where another process placed the same run's export there
    first. Anything else found there by then is refused as check_destination refuses it. An empty folder at `out`
    (`--out .`, say) stays the folder it is (renamed over, it would leave a shell inside it in a deleted folder):
    the files move into it, config.json last, so export_of finds it complete or not at all."""
    if out.is_dir() and not any(out.iterdir()):
        for file in sorted(partial.iterdir(), key=lambda f: f.name == "config.json"):
            os.replace(file, out / file.name)
        return True
    try:
        os.rename(partial, out)
        return True
    except OSError as e:
        if e.errno not in (errno.ENOTEMPTY, errno.EEXIST, errno.ENOTDIR):
            raise
    if export_of(out) == run_id:
        return False
    check_destination(out)  # refuses what is there now; emptied meanwhile, it takes the export
    os.rename(partial, out)
    return True


#: Steps lerobot-eval overrides in every preprocessor it loads (lerobot/scripts/lerobot_eval.py): a saved
#: preprocessor without either fails there with a KeyError.
EVAL_OVERRIDDEN_STEPS = ("device_processor", "rename_observations_processor")


def check_processors(folder: Path) -> None:
    """Refuse, in one line, a saved preprocessor that lerobot-eval could not load."""
    path = folder / "policy_preprocessor.json"
    names = {s.get("registry_name") for s in json.loads(path.read_text())["steps"]}
    missing = [n for n in EVAL_OVERRIDDEN_STEPS if n not in names]
    if missing:
        raise ExportError(f"{path}: has no {', '.join(missing)} step, which lerobot-eval overrides")
