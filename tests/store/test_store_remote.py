"""Caches in an object store, against a real S3 endpoint: moto's server on 127.0.0.1, real HTTP, no in-process
mocks. Extract into s3://, ls/info/verify remote, push and pull both ways, kill -9 mid-push then resume, a flipped
byte in a remote shard (named by verify and checksum-on-read, refused by pull), two concurrent writers on one key
(local and S3), fit reading only what it needs from the bucket, a read-only root used by a non-root user."""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from functools import partial
from pathlib import Path

import boto3
import numpy as np
import pytest
import torch
from fixtures.s3 import bucket_objects
from helpers.backbones import tiny
from helpers.caches import CAMERAS, assert_same_cache, folder_files, rekeyed, synthetic_cache
from helpers.datasets import Written
from helpers.requests import extract_request

from graftcache.cli import main
from graftcache.errors import CacheError
from graftcache.extract import extract
from graftcache.fit.data import load_lowdim
from graftcache.fit.feed import SplitFeed
from graftcache.fit.local import Fitter
from graftcache.fit.run import FitRequest
from graftcache.fit.stream import FeatureSource, read_blocks
from graftcache.store import FeatureCache, cache_key, list_caches, open_root, scan_caches
from graftcache.store.cache import MisplacedCache
from graftcache.store.push_pull import copy_cache
from graftcache.store.readthrough import reading_root

ENCODER = "timm:vit_tiny_patch16_224"
GRAFTCACHE = Path(sys.executable).with_name("graftcache")


def _quiet(_: str) -> None:
    pass


def _put_object(url: str, rel: str, data: bytes) -> None:
    bucket, prefix = url[len("s3://"):].split("/", 1)
    boto3.client("s3").put_object(Bucket=bucket, Key=f"{prefix}/{rel}", Body=data)


_req = partial(extract_request, encoder=ENCODER, grids=("2x2",), batch_size=8, block_frames=2)


@pytest.fixture(scope="module")
def local(v3_image: Written, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, str]:  # noqa: F811
    """A complete local cache (9 blocks of 2 frames per array) and its key."""
    root = tmp_path_factory.mktemp("local")
    return root, extract(_req(v3_image.root, root), log=_quiet).key


def _features(cache: FeatureCache) -> dict[str, np.ndarray]:
    return {name: cache.group[name][...] for name in cache.layout["arrays"]}


def test_extract_into_s3_equals_local_and_ls_info_verify_read_it(
        s3: str, local: tuple[Path, str], v3_image: Written, capsys: pytest.CaptureFixture) -> None:  # noqa: F811
    result = extract(_req(v3_image.root, s3), log=_quiet)
    assert result.key == local[1] and result.path == f"{s3}/{result.key}"  # the same identity fields, the same key
    objects = bucket_objects(s3)
    assert json.loads(objects[f"{result.key}/zarr.json"])["attributes"]["complete"] is True
    assert not [k for k in objects if "/_progress/" in k]  # markers removed once complete
    remote, here = FeatureCache(result.path), FeatureCache(local[0] / local[1])
    assert remote.attrs["checksums"] == here.attrs["checksums"]
    for name, values in _features(here).items():
        np.testing.assert_array_equal(remote.group[name][...], values)
    assert main(["ls", "--cache", s3]) == 0
    out = capsys.readouterr().out
    assert result.key in out and "complete" in out and ENCODER in out
    assert main(["info", result.key, "--cache", s3]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["complete"] is True and info["encoder"]["name"] == ENCODER and info["layout"]["n_blocks"] == 9
    assert main(["verify", result.key, "--cache", s3]) == 0
    assert "all checksums match" in capsys.readouterr().out
    assert extract(_req(v3_image.root, s3), log=_quiet).reused


def test_sharded_extract_into_s3_equals_one_local_process(s3: str, local: tuple[Path, str],
                                                          v3_image: Written) -> None:
    root, key = local
    lines: list[str] = []
    assert not extract(_req(v3_image.root, s3, shard=(1, 2)), log=lines.append).complete
    assert "misses 4 of 9 blocks, of 1 of 2 shards (0)" in lines[-1]
    last = extract(_req(v3_image.root, s3, shard=(0, 2)), log=_quiet)
    assert last.complete and not last.reused and last.key == key and last.frames_encoded == 8  # 4 blocks of 2
    objects = bucket_objects(s3)
    assert_same_cache({rel[len(key) + 1:]: data for rel, data in objects.items() if rel.startswith(f"{key}/")},
                      folder_files(root / key))
    leases = {rel.split("/")[0] for rel in objects if not rel.startswith(f"{key}/")}
    assert leases == {f"{key}.lease", f"{key}.shard-0-of-2.lease", f"{key}.shard-1-of-2.lease"}  # beside the cache


def test_push_and_pull_both_ways_verified_and_idempotent(s3: str, local: tuple[Path, str], tmp_path: Path) -> None:
    root, key = local
    pushed = copy_cache(open_root(root), open_root(s3), key, log=_quiet)
    n_objects = len([k for k in bucket_objects(s3) if k.startswith(f"{key}/")])
    assert not pushed.skipped and pushed.objects == n_objects - 1  # every object but zarr.json, then zarr.json
    assert pushed.bytes == sum(len(v) for k, v in bucket_objects(s3).items()
                               if k.startswith(f"{key}/") and k != f"{key}/zarr.json")
    again = copy_cache(open_root(root), open_root(s3), key, log=_quiet)
    assert again.skipped and again.objects == 0  # a key that exists and verifies is not copied again
    assert main(["pull", key, s3, "--cache", str(tmp_path / "pulled")]) == 0
    pulled = FeatureCache(tmp_path / "pulled" / key)
    assert pulled.complete and pulled.verify() == []
    for name, values in _features(FeatureCache(root / key)).items():
        np.testing.assert_array_equal(pulled.group[name][...], values)
    shard = tmp_path / "pulled" / key / "features" / "image" / "2x2" / "c" / "4" / "0" / "0"
    damaged = bytearray(shard.read_bytes())
    damaged[len(damaged) // 3] ^= 0x01
    shard.write_bytes(bytes(damaged))
    repaired = copy_cache(open_root(s3), open_root(tmp_path / "pulled"), key, log=_quiet)
    assert repaired.objects == 1 and not repaired.skipped and pulled.verify() == []  # only the damaged shard
    # a pulled cache pushes to another prefix: both directions through the CLI
    assert main(["push", key, f"{s3}-mirror", "--cache", str(tmp_path / "pulled")]) == 0
    assert FeatureCache(f"{s3}-mirror/{key}").verify() == []


def test_another_cache_under_a_key_is_refused(s3: str, local: tuple[Path, str]) -> None:
    """A bucket folder named KEY whose manifest hashes to another key is not cache KEY: verify says so naming
    both keys, and a push of the real KEY refuses to overwrite it (the bucket is left as it was)."""
    root, key = local
    copy_cache(open_root(root), open_root(s3), key, log=_quiet)
    cache = FeatureCache(f"{s3}/{key}")
    cache.group.attrs["manifest"] = {**cache.manifest.to_dict(), "grids": ["3x3"]}  # another cache, copied in by hand
    own = cache_key(cache.group.attrs["manifest"])
    before = bucket_objects(s3)
    with pytest.raises(MisplacedCache, match=f"not cache {key}: its manifest hashes to {own}"):
        copy_cache(open_root(root), open_root(s3), key, log=_quiet)
    assert main(["verify", key, "--cache", s3]) == 2
    assert bucket_objects(s3) == before


def test_kill_9_mid_push_then_resume(s3: str, local: tuple[Path, str]) -> None:
    root, key = local
    proc = subprocess.Popen([str(GRAFTCACHE), "push", key, s3, "--cache", str(root)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, env={**os.environ})
    bucket, prefix = s3[len("s3://"):].split("/", 1)
    client = boto3.client("s3")
    deadline = time.time() + 120
    while time.time() < deadline:  # the pending zarr.json (complete: false) is the first object written
        listed = client.list_objects_v2(Bucket=bucket, Prefix=f"{prefix}/{key}/").get("KeyCount", 0)
        if listed > 1:
            break
        time.sleep(0.002)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    before = bucket_objects(s3)
    assert json.loads(before[f"{key}/zarr.json"])["attributes"]["complete"] is False  # killed before publishing
    assert not FeatureCache(f"{s3}/{key}").complete
    time.sleep(2.5)  # the killed writer's lease expires (GRAFTCACHE_LEASE_S=2)
    resumed = copy_cache(open_root(root), open_root(s3), key, log=_quiet)
    present = len([k for k in before if k.startswith(f"{key}/") and k != f"{key}/zarr.json"])
    assert resumed.already_there == present and present > 0
    assert resumed.objects + resumed.already_there == len(open_root(root).sizes(f"{key}/")) - 1
    assert FeatureCache(f"{s3}/{key}").verify() == []


def test_a_flipped_byte_in_a_remote_shard_is_named_and_refused(
        s3: str, local: tuple[Path, str], tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    root, key = local
    copy_cache(open_root(root), open_root(s3), key, log=_quiet)
    shard = f"{key}/features/image/2x2/c/3/0/0"
    data = bytearray(bucket_objects(s3)[shard])
    data[len(data) // 3] ^= 0x01
    _put_object(s3, shard, bytes(data))
    where = "features/image/2x2 frames 6-7"
    assert main(["verify", key, "--cache", s3]) == 1
    assert where in capsys.readouterr().out
    assert main(["pull", key, s3, "--cache", str(tmp_path / "pulled")]) == 2
    err = capsys.readouterr().err
    assert where in err and "failed verification" in err and len(err.strip().splitlines()) == 1
    pulled = FeatureCache(tmp_path / "pulled" / key)
    assert not pulled.complete and not (tmp_path / "pulled" / shard).exists()
    with pytest.raises(CacheError, match=r"features/image/2x2 frames 6-7 \(block 3\)"):  # checksum on read
        FeatureCache.in_root(reading_root(s3), key).read_features("image", "2x2", np.arange(18))


@pytest.mark.parametrize("where", ["local", "s3"])
def test_two_concurrent_writers_on_one_key(where: str, request: pytest.FixtureRequest, tmp_path: Path,
                                           v3_image: Written) -> None:  # noqa: F811
    root = request.getfixturevalue("s3") if where == "s3" else str(tmp_path / "root")
    cmd = [str(GRAFTCACHE), "extract", "--dataset", str(v3_image.root), "--encoder", ENCODER, "--random-init",
           "--grids", "2x2", "--episodes", "0", "--num-workers", "0", "--batch-size", "8", "--block-frames", "2",
           "--no-progress",
           "--cache", root]
    procs = [subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True) for _ in range(2)]
    outs = [p.communicate(timeout=300)[0] for p in procs]
    assert [p.returncode for p in procs] == [0, 0], outs
    assert sum("wrote " in o for o in outs) == 1 and sum("reusing complete cache" in o for o in outs) == 1, outs
    (cache,) = list_caches(root)
    assert cache.complete and cache.verify() == []


def test_fit_reads_a_remote_cache_through_local_copies(
        s3: str, v3_image: Written, tmp_path: Path) -> None:  # noqa: F811
    root = tmp_path / "local"
    key = extract(_req(v3_image.root, root, grids=("4x4", "2x2")), log=_quiet).key
    copy_cache(open_root(root), open_root(s3), key, log=_quiet)
    _put_object(s3, "junk/zarr.json", b"{not json")  # a broken cache beside it: listed as broken, never used
    assert [b.key for b in scan_caches(s3)[1]] == ["junk"]
    policy = tmp_path / "policy"
    tiny("smolvla").save(policy)
    rows = {}
    for name, cache in (("local", str(root)), ("s3", s3)):
        req = FitRequest(backbone="smolvla", encoder=ENCODER, suite="libero_spatial", policy=str(policy),
                         seeds=(0,), steps=2, batch_size=4, eval_fraction=0.5, eval_frames=4, num_denoise_steps=2,
                         cache=cache, progress=False, results=str(tmp_path / f"{name}.parquet"), command="pytest")
        fitter = Fitter(req, log=_quiet)
        (rows[name],) = fitter.run()
        if name == "s3":
            fetched = fitter.plan.root.fetched_bytes
    assert rows["s3"]["eval_mse"] == rows["local"]["eval_mse"]
    mirror = fitter.plan.root.local.path / key
    copied = {p.relative_to(mirror).as_posix(): p.stat().st_size for p in mirror.rglob("*") if p.is_file()}
    assert fetched == sum(copied.values())
    spatial = {int(r) // 2 for r in load_lowdim(FeatureCache(root / key), "libero_spatial", chunk=1).rows}
    shards = {rel for rel in copied if rel.startswith("features/") and not rel.endswith("zarr.json")}
    assert shards and all(rel.split("/")[2] == "4x4" and int(rel.split("/")[4]) in spatial for rel in shards)
    assert fetched < sum(open_root(s3).sizes(f"{key}/").values())  # the 2x2 grid, the other suite: never read
    refit = Fitter(dataclasses.replace(req, seeds=(1,)), log=_quiet)
    refit.run()
    assert refit.plan.root.fetched_bytes == 0  # the local copies serve the next run
    assert (tmp_path / "runs").is_dir() and not [k for k in bucket_objects(s3) if "/runs/" in k]


def test_a_read_only_root_serves_a_non_root_user_and_is_left_unchanged(
        local: tuple[Path, str], tmp_path: Path) -> None:
    """uid nobody with CAP_DAC_READ_SEARCH only: it reads everything (the venv lives under /root) and may write
    nothing it does not own, like a colleague reading another user's cache root."""
    if os.getuid() != 0 or shutil.which("setpriv") is None:
        pytest.skip("needs root and setpriv to run a command as another user")
    root, key = local
    shared = Path(tempfile.mkdtemp(prefix="graftcache-ro-"))
    try:
        ro = shared / "ro"
        shutil.copytree(root / key, ro / key)
        os.chmod(shared, 0o755)
        work = shared / "work"
        work.mkdir(mode=0o777)
        os.chmod(work, 0o777)
        tiny("smolvla").save(shared / "policy")
        before = {p: p.stat().st_mtime_ns for p in ro.rglob("*")}
        env = {**os.environ, "HOME": str(work), "GRAFTCACHE_HOME": str(work / "home"), "HF_HOME": str(work / "hf"),
               "HF_HUB_CACHE": str(work / "hf" / "hub"), "HF_LEROBOT_HOME": str(work / "hf" / "lerobot"),
               "PYTHONPATH": os.pathsep.join(sys.path)}
        as_nobody = ["setpriv", "--reuid=nobody", "--regid=nogroup", "--clear-groups",
                     "--inh-caps=+dac_read_search", "--ambient-caps=+dac_read_search", str(GRAFTCACHE)]

        def run(*args: str) -> subprocess.CompletedProcess:
            return subprocess.run([*as_nobody, *args], capture_output=True, text=True, cwd=work, env=env, timeout=300)

        probe = subprocess.run([*as_nobody[:-1], "touch", str(ro / "probe")], capture_output=True)
        assert probe.returncode != 0  # the root really is read-only for this user
        assert key in run("ls", "--cache", str(ro)).stdout
        assert run("info", key, "--cache", str(ro)).returncode == 0
        assert run("verify", key, "--cache", str(ro)).returncode == 0
        fit = run("fit", "--backbone", "smolvla", "--policy", str(shared / "policy"), "--encoder", ENCODER, "--suite",
                  "libero_spatial", "--seeds", "1", "--steps", "2", "--batch-size", "4", "--eval-fraction", "0.5",
                  "--eval-frames", "4", "--num-denoise-steps", "2", "--cache", str(ro), "--results",
                  str(work / "r.parquet"), "--no-progress")
        assert fit.returncode == 0, fit.stderr
        assert (work / "r.parquet").is_file() and (work / "runs").is_dir()
        assert {p: p.stat().st_mtime_ns for p in ro.rglob("*")} == before  # nothing written, nothing touched
    finally:
        shutil.rmtree(shared, ignore_errors=True)


def test_ls_flags_a_broken_cache_and_lists_the_healthy_ones(local: tuple[Path, str], tmp_path: Path,
                                                            capsys: pytest.CaptureFixture) -> None:
    root, key = local
    shutil.copytree(root / key, tmp_path / key)
    damaged = tmp_path / f"{key.rsplit('-', 1)[0]}-{'0' * 16}"  # a key's name whose zarr.json is cut short
    shutil.copytree(root / key, damaged)
    (damaged / "zarr.json").write_text('{"zarr_format": 3, "attributes": {"manifest": ')
    partial = rekeyed(root / key, tmp_path, lambda m: {k: v for k, v in m.items() if k != "n_frames"}
                      | {"weights_sha256": "other"}).name
    assert main(["ls", "--cache", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    rows = {line.split()[1]: line for line in out.splitlines() if line.startswith("│") and len(line.split()) > 2}
    assert "complete" in rows[key] and "BROKEN" not in rows[key]
    assert "BROKEN" in rows[damaged.name] and "BROKEN" in rows[partial]
    flat = " ".join(out.replace("│", " ").split())  # a long reason wraps inside its cell
    assert "zarr.json is not a feature cache" in flat and "manifest of format 3 lacks n_frames" in flat
    assert [c.key for c in list_caches(tmp_path)] == [key]
    assert torch.equal(FeatureCache(tmp_path / key).read_features("image", "2x2"),
                       FeatureCache(root / key).read_features("image", "2x2"))


def test_object_store_workers_check_each_block_once_per_fit(s3: str, tmp_path: Path,
                                                              monkeypatch: pytest.MonkeyPatch) -> None:
    """Workers for an object-store root start from a fork server and inherit nothing: the blocks the first
    stream's worker checked travel with the fit's reader to the next streams' workers, which never check them
    again (each block's checksum is computed once per fit, as the docs say)."""
    monkeypatch.setenv("GRAFTCACHE_HOME", str(tmp_path / "home"))  # the read-through copies
    local = synthetic_cache(tmp_path / "local", (9, 7, 12), block_frames=4)
    copy_cache(local.root, open_root(s3), local.key, log=_quiet)
    cache = FeatureCache.in_root(reading_root(s3), local.key)
    feed = SplitFeed(load_lowdim(cache, "libero_spatial", chunk=2), FeatureSource.of(cache, CAMERAS, (2, 2)),
                     int(cache.layout["block_frames"]))
    reported = [b for _ in range(3)  # three streams of one fit (epochs, cells), each with a new worker
                for block in read_blocks(feed.features(seed=None), 1) for b in block.verified]
    features = {(str(cache.path), f"features/{c}/4x4", b) for c in CAMERAS for b in range(cache.layout["n_blocks"])}
    assert sorted(b for b in reported if b[2] >= 0) == sorted(features)  # every block, each checked once
    assert feed.source.reader.checks.count == len(reported) and set(reported) <= feed.source.reader.checks.done
