"""`extract --shard i/N`: N processes fill one cache together; the result is byte-identical to one process.

Every file under the cache folder is compared with a single-process run of the same request, except the group's
zarr.json, whose attributes may differ only in what records time and command (created_at, completed_at, run).
"""

from __future__ import annotations

import dataclasses
import os
import signal
import subprocess
import sys
from collections.abc import Iterator
from functools import partial
from pathlib import Path

import pytest
from helpers.caches import assert_same_cache, folder_files
from helpers.probes import hang_after_blocks, kill_after_blocks, start_process
from helpers.requests import extract_request

from graftcache.cli import main
from graftcache.codecs import shard_value
from graftcache.errors import GraftcacheError
from graftcache.extract import extract, shard_blocks
from graftcache.recipe import SECTION_KEYS
from graftcache.store import FeatureCache

SAMPLE = Path(__file__).resolve().parents[2] / "data" / "libero_sample"
ENCODER = "timm:test_vit"  # timm's own test ViT: a real ViT architecture at 160 px, the cheapest to run
GRAFTCACHE = Path(sys.executable).with_name("graftcache")
#: Episodes 0-1 of the sample (101 frames) in blocks of 8: 13 blocks, both cameras.
FLAGS = ("--encoder", ENCODER, "--random-init", "--dataset", str(SAMPLE), "--episodes", "0-1", "--grids", "2x2",
         "--block-frames", "8", "--batch-size", "8", "--num-workers", "0", "--no-progress")


#: `_req(cache, **settings)`: the sample's first two episodes into the cache root `cache`.
_req = partial(extract_request, SAMPLE, encoder=ENCODER, episodes=(0, 1), grids=("2x2",), block_frames=8, batch_size=8)


def _cli(cache: Path, shard: str) -> list[str]:
    return [str(GRAFTCACHE), "extract", *FLAGS, "--cache", str(cache), "--shard", shard]


def _env() -> dict[str, str]:
    """Two shard processes on CI's two cores: one torch thread each (graftcache.runtime.set_main_threads)."""
    return {**os.environ, "HF_HUB_OFFLINE": "1", "OMP_NUM_THREADS": "1"}


@pytest.fixture(scope="module", autouse=True)
def _one_thread_each() -> Iterator[None]:
    """One torch thread in this process's extractions too, as in the shard processes (`_env`): a tiny ViT on a
    shared 2-core machine is several times faster on one thread than on two."""
    import torch

    threads = torch.get_num_threads()
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("OMP_NUM_THREADS", "1")
        yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def single(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The same request extracted by one process, without --shard."""
    result = extract(_req(tmp_path_factory.mktemp("single")), log=lambda _: None)
    assert result.complete and not result.reused
    return Path(result.path)


def _assert_same_cache(got: Path, want: Path) -> None:
    assert_same_cache(folder_files(got), folder_files(want))


def test_shards_cover_every_block_once() -> None:
    for n_blocks in (1, 5, 20, 21):
        for shards in (1, 2, 3, 7):
            ranges = [shard_blocks(n_blocks, i, shards) for i in range(shards)]
            assert [b for r in ranges for b in r] == list(range(n_blocks))
            assert max(map(len, ranges)) - min(map(len, ranges)) <= 1


@pytest.mark.slow
def test_two_concurrent_shard_processes_equal_one_process(single: Path, tmp_path: Path) -> None:
    procs = [subprocess.Popen(_cli(tmp_path, f"{i}/2"), env=_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                              text=True) for i in range(2)]
    outs = [p.communicate(timeout=600) for p in procs]
    assert [p.returncode for p in procs] == [0, 0], [err for _, err in outs]
    assert all(out.strip().splitlines()[-1] == single.name for out, _ in outs)  # both print the key
    assert sum(f"wrote {single.name}" in out for out, _ in outs) >= 1
    _assert_same_cache(tmp_path / single.name, single)
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(single.name + ".shard")) == [
        f"{single.name}.shard-0-of-2.lock", f"{single.name}.shard-1-of-2.lock"]  # beside the cache, never in it


KEPT = 2  # blocks shard 0 writes before its writer hangs and the test kills it


@pytest.mark.slow
def test_a_killed_shard_reruns_and_the_last_shard_completes(single: Path, tmp_path: Path) -> None:
    n_blocks = FeatureCache(single).layout["n_blocks"]
    first = set(shard_blocks(n_blocks, 0, 2))
    proc = start_process(_cli(tmp_path, "0/2")[1:], env={"OMP_NUM_THREADS": "1"}, prelude=hang_after_blocks(KEPT))
    assert kill_after_blocks(proc, tmp_path, KEPT).code == -signal.SIGKILL
    killed = FeatureCache(tmp_path / single.name)
    written = killed.blocks_done()
    assert not killed.complete and len(written) == KEPT and written < first  # part of shard 0 only
    # what a write killed half-way leaves (zarr's temporary file): the cache that completes must not hold it
    leftover = tmp_path / single.name / "features/image/2x2/c/0/0/0.0123456789abcdef.partial"
    leftover.parent.mkdir(parents=True, exist_ok=True)
    leftover.write_bytes(b"half a shard")

    lines: list[str] = []
    other = extract(_req(tmp_path, shard=(1, 2)), log=lines.append)
    assert not other.complete and not other.reused and other.frames_encoded > 0
    missing = len(first - written)
    assert f"misses {missing} of {n_blocks} blocks, of 1 of 2 shards (0)" in lines[-1]
    assert not FeatureCache(tmp_path / single.name).complete

    lines.clear()
    rerun = extract(_req(tmp_path, shard=(0, 2)), log=lines.append)
    assert rerun.complete and not rerun.reused
    assert f"shard 0/2 of {single.name}: {len(written) + len(shard_blocks(n_blocks, 1, 2))}/{n_blocks} blocks" \
        in "\n".join(lines)
    assert rerun.frames_encoded == missing * 8  # only the killed shard's unwritten blocks (all full)
    _assert_same_cache(tmp_path / single.name, single)
    again = extract(_req(tmp_path, shard=(1, 2)), log=lambda _: None)
    assert again.complete and again.reused and again.frames_encoded == 0


@pytest.mark.parametrize("text", ["2/2", "-1/2", "1", "a/2", "0/0", "1/2/3", "0/-1"])
def test_bad_shard_values_are_one_line_errors(text: str, capsys: pytest.CaptureFixture) -> None:
    with pytest.raises(SystemExit) as stopped:
        main(["extract", *FLAGS, f"--shard={text}"])
    assert stopped.value.code == 2
    assert capsys.readouterr().err.strip().splitlines()[-1] == (
        f"graftcache extract: error: argument --shard: {text!r} is not i/N with 0 <= i < N (e.g. 0/4 ... 3/4)")


def test_requests_check_shards_and_recipes_never_set_them(tmp_path: Path) -> None:
    assert shard_value("3/4") == (3, 4)
    for bad in ((2, 2), (-1, 2), (0, 0)):
        with pytest.raises(GraftcacheError, match=r"shard = .* must be i/N with 0 <= i < N"):
            _req(tmp_path, shard=bad)
    assert dataclasses.replace(_req(tmp_path), shard=(1, 3)).shard == (1, 3)
    assert "shard" not in SECTION_KEYS["extract"]
