"""Executors. The ray executor on a local Ray instance (tests/fixtures/ray_cluster.py): a sweep writes the
local executor's rows, a worker SIGKILLed mid-cell costs only its own cell, a sharded extraction writes the local
extraction's bytes, and an error raised in a task is the command's one line. Without a cluster: how settings
reach the executors (recipe section, flags) and that Ray is imported only when chosen."""

from __future__ import annotations

import builtins
import dataclasses
import importlib
import os
import pickle
import signal
import subprocess
import sys
import textwrap
import threading
from dataclasses import dataclass
from pathlib import Path

import polars as pl
import pytest
from fixtures.ray_cluster import JOB_MARKER
from helpers.caches import assert_same_cache, folder_files
from helpers.datasets import Written

from graftcache import results
from graftcache.cli import main
from graftcache.errors import ExecutorError
from graftcache.executors import get_executor
from graftcache.extract import ExtractRequest, extract
from graftcache.recipe import Recipe, RecipeError, load_recipe
from graftcache.requests import ExecutorSettings
from graftcache.sweep import run_sweep

RECIPE = """
    name = "ray"
    dataset = "{dataset}"
    results = "{results}"
    cache = "{cache}"
    suites = ["libero_spatial"]
    seeds = [0, 1]
    controls = ["zero-image"]
    [[backbones]]
    name = "smolvla"
    [[encoders]]
    name = "timm:vit_tiny_patch16_224"
    random_init = true
    seed = 3
    [extract]
    batch_size = 8
    num_workers = 0
    [fit]
    steps = {steps}
    batch_size = 4
    eval_frames = 4
    num_denoise_steps = 2
    [train_tiny]
    steps = 2
    batch_size = 4
"""
#: The columns both executors must write alike: all but the cell's wall time and the command (the recipe's path).
SAME = [c for c in results.SCHEMA if c not in ("wall_s", "eval_seconds_per_frame", "command")]  # all but timings
STEPS = 10  # a cell takes a few seconds: long enough to be caught running


@dataclass
class LocalSweep:
    folder: Path
    dataset: Path
    rows: pl.DataFrame

    def recipe(self, name: str, cells_per_pass: int | None = None) -> Recipe:
        """The recipe, writing its results under `name`/; its cache and tiny policy are shared."""
        path = self.folder / f"{name}.toml"
        text = textwrap.dedent(RECIPE).format(dataset=self.dataset, cache=self.folder / "cache",
                                              results=self.folder / name / "results.parquet", steps=STEPS)
        if cells_per_pass is not None:  # into the [fit] section
            text = text.replace("[train_tiny]", f"cells_per_pass = {cells_per_pass}\n[train_tiny]")
        path.write_text(text)
        return load_recipe(path)


@pytest.fixture(scope="module")
def local_sweep(v3_video: Written, tmp_path_factory: pytest.TempPathFactory) -> LocalSweep:
    """The recipe swept by the local executor (4 cells: 2 seeds x plain and zero-image), with one torch thread
    as in a Ray task given 1 CPU, so that both add their floats in the same order."""
    sweep = LocalSweep(tmp_path_factory.mktemp("ray_sweep"), v3_video.root, results.empty())
    recipe = sweep.recipe("local")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("OMP_NUM_THREADS", "1")
        run_sweep(recipe, log=lambda _: None)
    sweep.rows = results.read(recipe.results).sort("run_id")
    assert sweep.rows.height == recipe.n_rows == 4
    return sweep


def _assert_same_rows(recipe: Recipe, local: pl.DataFrame) -> None:
    rows = results.read(recipe.results).sort("run_id")
    assert rows.select(SAME).to_dicts() == local.select(SAME).to_dicts()
    assert set(rows["command"]) == {f"graftcache sweep {recipe.path}"}


def test_recipe_table_and_flags_choose_the_executor(tmp_path: Path, v2_pi: Written,
                                                    capsys: pytest.CaptureFixture) -> None:
    path = tmp_path / "r.toml"  # a dataset that exists: the dry run opens it, as the sweep would
    base = textwrap.dedent(RECIPE).format(dataset=v2_pi.root, results="r.parquet", cache="c", steps=1)
    path.write_text(base + '[executor]\nexecutor = "ray"\naddress = "ray://head:10001"\ngpus_per_task = 0.25\n')
    recipe = load_recipe(path)
    assert recipe.executor_settings == ExecutorSettings(executor="ray", address="ray://head:10001", gpus_per_task=0.25)
    assert main(["sweep", str(path), "--dry-run"]) == 0
    assert "executor  ray at ray://head:10001" in capsys.readouterr().out
    assert main(["sweep", str(path), "--dry-run", "--executor", "local"]) == 0  # a flag given wins over the table
    assert "executor  local at ray://head:10001" in capsys.readouterr().out
    path.write_text(base + '[executor]\nexecutor = "slurm"\n')
    with pytest.raises(RecipeError, match=r"r.toml \[executor\]: executor = 'slurm' is not one of local, ray"):
        load_recipe(path)
    path.write_text(base + "[executor]\ngpus_per_task = 1.5\n")
    with pytest.raises(RecipeError, match=r"\[executor\]: gpus_per_task = 1.5 must be between 0 and 1 or a whole"):
        load_recipe(path)
    with pytest.raises(SystemExit):
        main(["extract", "--encoder", "x", "--dataset", "x", "--executor", "ray", "--cpus-per-task", "0"])
    assert "argument --cpus-per-task: 0.0 must be > 0" in capsys.readouterr().err


def test_ray_is_imported_only_when_chosen() -> None:
    code = ("import sys; from graftcache.cli import build_parser; from graftcache.executors import get_executor; "
            "from graftcache.requests import ExecutorSettings; build_parser(); get_executor(ExecutorSettings()); "
            "get_executor(ExecutorSettings(executor='ray')); assert 'ray' not in sys.modules; "
            "import graftcache.executors.ray_cluster; assert 'ray' in sys.modules")  # (the check sees an import)
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, check=False)
    assert done.returncode == 0, done.stderr


def test_a_local_ray_instance_keeps_its_token_in_the_cache_folder(tmp_path: Path) -> None:
    """A Ray instance the ray executor starts here authenticates with a token in the local cache folder
    (ray/auth_token, 0600, made once and kept), and nothing is written to ~/.ray (Ray's default); where Ray's own
    settings name a token or a mode, they stand."""
    home, cache = tmp_path / "home", tmp_path / "cache"
    home.mkdir()
    env = {k: v for k, v in os.environ.items() if not k.startswith("RAY_AUTH")}
    env.update(HOME=str(home), GRAFTCACHE_HOME=str(cache), RAY_USAGE_STATS_ENABLED="0")
    script = textwrap.dedent("""
        import os, ray
        from graftcache.executors.ray_cluster import connect
        from graftcache.requests import ExecutorSettings
        connect(ExecutorSettings(), lambda line: None)
        print(ray.get(ray.remote(lambda: 6 * 7).remote()), os.environ["RAY_AUTH_TOKEN_PATH"])
        ray.shutdown()
    """)
    outputs = [subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=300)
               for _ in range(2)]
    token = cache / "ray" / "auth_token"
    assert [o.stdout.split() for o in outputs] == [["42", str(token)]] * 2, outputs[0].stderr[-2000:]
    assert token.stat().st_mode & 0o777 == 0o600 and len(token.read_text()) == 64
    assert not (home / ".ray").exists()
    from graftcache.executors.ray_cluster import use_local_token

    os.environ["RAY_AUTH_MODE"] = "disabled"
    try:
        assert use_local_token() is None
    finally:
        del os.environ["RAY_AUTH_MODE"]


def test_ray_task_options_refuse_what_ray_cannot_place() -> None:
    from graftcache.executors.ray_cluster import task_options

    assert task_options(ExecutorSettings(executor="ray"), "cuda") == {
        "num_cpus": 1.0, "num_gpus": 1.0, "max_retries": 3, "retry_exceptions": False}
    assert task_options(ExecutorSettings(executor="ray", gpus_per_task=0.5, cpus_per_task=4), "cpu")["num_gpus"] == 0.5
    assert task_options(ExecutorSettings(executor="ray"), "cpu")["num_gpus"] == 0
    with pytest.raises(ExecutorError, match="--device cuda:1 with the ray executor: .* pass --device cuda"):
        task_options(ExecutorSettings(executor="ray"), "cuda:1")
    with pytest.raises(ExecutorError, match="--device cuda with --gpus-per-task 0: a task would get no GPU"):
        task_options(ExecutorSettings(executor="ray", gpus_per_task=0), "cuda")


@pytest.mark.parametrize("module, name", [("graftcache.executors.ray_fit", "fit_cells"),
                                          ("graftcache.executors.ray_extract", "extract_shard")])
def test_ray_tasks_ship_their_function_by_reference(module: str, name: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """A task's function travels as "module.name", so a worker keeps its own module state (loaded backbones), and
    nothing of the driver's goes with it: not even a `print` that something in the driver has replaced, which a
    function shipped by value (with its globals' objects) cannot pickle."""
    from ray import cloudpickle

    task_module = importlib.import_module(module)
    monkeypatch.setattr(builtins, "print", lambda *args, **kwargs: None)
    shipped = cloudpickle.dumps(getattr(task_module, f"{name}_task")._function)
    assert pickle.loads(shipped) is getattr(task_module, name)
    assert len(shipped) < 200, len(shipped)


@pytest.mark.slow
def test_an_error_raised_in_a_task_is_the_commands_one_line(ray_cluster: str, tmp_path: Path,
                                                            capsys: pytest.CaptureFixture) -> None:
    (tmp_path / "ds").mkdir()  # a folder, but no LeRobot dataset: the shard tasks' extract raises DatasetError
    code = main(["extract", "--encoder", "timm:vit_tiny_patch16_224", "--random-init",
                 "--dataset", str(tmp_path / "ds"), "--cache", str(tmp_path / "cache"), "--executor", "ray",
                 "--no-progress"])
    out, err = capsys.readouterr()
    err = err.strip().splitlines()
    assert code == 2
    import ray

    # by default as many shards as the cluster runs tasks at once: one per CPU, 1 CPU per task
    cpus = int(ray.cluster_resources()["CPU"])
    said = f"ray: extract timm:vit_tiny_patch16_224 as {cpus} shard task(s), 0 GPU and 1 CPU each"
    assert said in out + "\n".join(err)
    assert err[-1].startswith(f"graftcache extract: error: {tmp_path / 'ds'}") and "Traceback" not in "\n".join(err)


@pytest.mark.slow
def test_ray_sweep_resumes_and_writes_the_local_rows(ray_cluster: str, local_sweep: LocalSweep) -> None:
    recipe = local_sweep.recipe("ray")
    # a driver of this recipe killed after its first row: that cell is in the results file, the other three are not
    command = pl.lit(f"graftcache sweep {recipe.path}")
    results.append(recipe.results, local_sweep.rows.head(1).with_columns(command=command))
    lines: list[str] = []
    run_sweep(recipe, log=lines.append, settings=ExecutorSettings(executor="ray"))
    assert ("ray: 3 cell task(s) to run; the other cells are in the results file already, or copied from a run of "
            "the same policy") in lines
    _assert_same_rows(recipe, local_sweep.rows)
    runs = Path(recipe.results).parent / "runs"  # projectors of the cells the tasks fitted, none of the skipped one
    assert sorted(p.name for p in runs.iterdir()) == sorted(local_sweep.rows["run_id"][1:])


@pytest.mark.slow
def test_a_fused_pass_on_ray_writes_the_local_executors_rows(ray_cluster: str, local_sweep: LocalSweep) -> None:
    """--cells-per-pass reaches the cluster: a Ray task is a pass of 2 cells, and its rows are the local executor's
    rows of the same passes."""
    local = local_sweep.recipe("local-fused", cells_per_pass=2)
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("OMP_NUM_THREADS", "1")
        run_sweep(local, log=lambda _: None)
    fused = results.read(local.results).sort("run_id")
    assert fused["cells_per_pass"].to_list() == [2] * 4
    recipe = local_sweep.recipe("ray-fused", cells_per_pass=2)
    lines: list[str] = []
    run_sweep(recipe, log=lines.append, settings=ExecutorSettings(executor="ray"))
    assert sum("its share of a pass of 2" in line for line in lines) == 4
    _assert_same_rows(recipe, fused)


@pytest.mark.slow
def test_two_ray_sweeps_of_one_recipe_compute_each_cell_once(ray_cluster: str, local_sweep: LocalSweep) -> None:
    """Two drivers of one recipe at once claim cells as the local executor does: each cell is computed by one."""
    recipe = local_sweep.recipe("two-drivers")
    logs: list[list[str]] = [[], []]
    errors: list[BaseException] = []

    def sweep(lines: list[str]) -> None:
        try:
            run_sweep(recipe, log=lines.append, settings=ExecutorSettings(executor="ray"))
        except BaseException as e:  # noqa: BLE001 - re-raised in the test's thread
            errors.append(e)

    drivers = [threading.Thread(target=sweep, args=(lines,)) for lines in logs]
    for driver in drivers:
        driver.start()
    for driver in drivers:
        driver.join()
    assert not errors, errors
    computed = [line for lines in logs for line in lines if "s on Ray" in line]
    assert len(computed) == 4, computed
    _assert_same_rows(recipe, local_sweep.rows)


def _running_cells(marker: str) -> list[int]:
    """Pids of this session's Ray workers running a cell now (Ray titles a busy worker `ray::<task name>`)."""
    pids = []
    for proc in Path("/proc").iterdir():
        try:
            busy = (proc / "cmdline").read_bytes().startswith(b"ray::fit_cell")
            ours = busy and f"{JOB_MARKER}={marker}".encode() in (proc / "environ").read_bytes().split(b"\0")
        except OSError:  # gone, or not ours to read
            continue
        if ours:
            pids.append(int(proc.name))
    return pids


@pytest.mark.slow
def test_a_worker_killed_mid_cell_costs_only_its_cell(ray_cluster: str, local_sweep: LocalSweep) -> None:
    recipe = local_sweep.recipe("killed")
    table, runs = Path(recipe.results), Path(recipe.results).parent / "runs"
    seen: dict[str, object] = {}
    stop = threading.Event()

    def kill_once_a_row_is_in() -> None:
        """SIGKILL a worker running a cell as soon as another cell's row is in the results file; note which
        cells were finished (in the file) then, and their projectors' mtimes."""
        while not stop.wait(0.05):
            finished = results.read(table)["run_id"].to_list() if table.exists() else []
            pids = _running_cells(ray_cluster) if finished else []
            if pids:
                mtimes = {r: (runs / r / "projector.safetensors").stat().st_mtime_ns for r in finished}
                os.kill(pids[0], signal.SIGKILL)
                seen.update(pid=pids[0], finished=mtimes)
                return

    killer = threading.Thread(target=kill_once_a_row_is_in, daemon=True)
    killer.start()
    try:
        run_sweep(recipe, log=lambda _: None, settings=ExecutorSettings(executor="ray", max_retries=2))
    finally:
        stop.set()
        killer.join()
    assert seen, "no cell was running after the first row was written: nothing was killed"
    with pytest.raises(ProcessLookupError):
        os.kill(int(seen["pid"]), 0)  # the worker really is gone
    assert 0 < len(seen["finished"]) < 4
    _assert_same_rows(recipe, local_sweep.rows)  # the killed cell was rerun, to the same row
    # cells finished before the kill were not fitted again: their projectors are the files written then
    assert {r: (runs / r / "projector.safetensors").stat().st_mtime_ns for r in seen["finished"]} == seen["finished"]


@pytest.mark.slow
def test_ray_extract_in_shard_tasks_writes_the_local_bytes(ray_cluster: str, v3_video: Written, tmp_path: Path,
                                                           monkeypatch: pytest.MonkeyPatch) -> None:
    req = ExtractRequest(dataset=str(v3_video.root), encoder="timm:vit_tiny_patch16_224", random_init=True,
                         grids=("2x2",), block_frames=4, batch_size=4, num_workers=0, progress=False)  # 5 blocks
    monkeypatch.setenv("OMP_NUM_THREADS", "1")  # one torch thread, as in a Ray task given 1 CPU: the same float sums
    local = extract(dataclasses.replace(req, cache=str(tmp_path / "local")), log=lambda _: None)
    lines: list[str] = []
    got = get_executor(ExecutorSettings(executor="ray", shards=2)).extract(
        dataclasses.replace(req, cache=str(tmp_path / "ray")), lines.append)
    assert "ray: extract timm:vit_tiny_patch16_224 as 2 shard task(s), 0 GPU and 1 CPU each" in lines
    assert (got.key, got.complete, got.reused, got.frames_encoded) == (local.key, True, False, local.n_frames)
    assert_same_cache(folder_files(Path(got.path)), folder_files(Path(local.path)))
