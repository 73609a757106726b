"""Results files with many writers (issue 24, item 2): concurrent appends and fits keep every row once, a reader
never sees a torn file, a row that cannot be written is kept in its run folder with a one-line error that says
how to merge it, a float seed is refused rather than rounded, and two sweeps of one recipe compute each cell once.
The lease file under all of it (graftcache/file_lease.py) is taken over only from a dead or silent holder.
Issue 29: a fused pass keeps every row, merging is idempotent, a wait for the lock is said, a results path that is
a link is followed, claims never outlive their cells, and an unwritable results folder does not lose the cell."""

from __future__ import annotations

import json
import os
import shlex
import shutil
import socket
import subprocess
import sys
import textwrap
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import polars as pl
import pytest
from helpers.backbones import tiny
from helpers.caches import dataset_cache
from helpers.datasets import Written
from helpers.tables import row

from graftcache import results
from graftcache.cli import main
from graftcache.errors import ResultsError
from graftcache.file_lease import FileLease
from graftcache.fit.passes import release_all
from graftcache.results.claims import cell_claim, claims_folder, drop_claims_folder, merge
from graftcache.results.writing import lock_path

SAMPLE = Path(__file__).resolve().parents[1] / "data" / "libero_sample"
SUITE, GRID, WIDTH = "libero_spatial", (4, 4), 16
ENCODER = f"synthetic-{WIDTH}"
ENV = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}

#: One writer process: 25 appends of one row each, then its exit code says whether any append raised.
WRITER = """
import sys
from helpers.tables import row
from graftcache import results
for seed in range(25):
    results.append(sys.argv[1], [row("smolvla", "libero_spatial", "enc" + sys.argv[2], seed, float(seed))])
"""

#: A reader polling the file until told to stop: every read must be a whole table, never fewer rows than before.
#: It pauses 20 ms between reads (about one append's time): a reader spinning flat out took a core from the writers
#: and doubled the test's time on 2 cores.
READER = """
import sys, pathlib, time
from graftcache import results
seen, reads = 0, 0
while not pathlib.Path(sys.argv[2]).exists():
    n = results.read(sys.argv[1]).height
    assert n >= seen, (n, seen)
    seen, reads = n, reads + 1
    time.sleep(0.02)
print(reads)
"""


@pytest.fixture(scope="module")
def world(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A tiny smolvla policy and a synthetic-feature cache of the sample dataset: the cheapest real fit."""
    root = tmp_path_factory.mktemp("writers")
    tiny("smolvla").save(root / "policy")
    dataset_cache(root / "cache", SAMPLE, SUITE, grid=GRID, width=WIDTH)
    return root


def fit_args(world: Path, results_path: Path, seeds: str, out: Path) -> list[str]:
    return ["fit", "--backbone", "smolvla", "--policy", str(world / "policy"), "--encoder", ENCODER, "--suite", SUITE,
            "--seed", seeds, "--steps", "2", "--batch-size", "4", "--num-workers", "0", "--eval-fraction", "0.5",
            "--eval-frames", "4", "--num-denoise-steps", "1", "--cache", str(world / "cache"), "--results",
            str(results_path), "--out", str(out), "--no-progress"]


def leftovers(folder: Path) -> list[str]:
    """What a finished results writer must not leave behind: temporary files, its lease and cell claims."""
    return sorted(p.name for p in folder.rglob("*") if p.name.endswith((".tmp", ".parquet.lock", ".claim"))
                  or ".stale." in p.name)


@pytest.mark.slow  # ~1 min on 2 cores: 4 writer processes, a reader and two fits (torch imports) at once
def test_four_writers_and_two_fits_keep_every_row(world: Path, tmp_path: Path) -> None:
    shared, stop = tmp_path / "results.parquet", tmp_path / "stop"
    # the fits overlap on seed 1: that cell must be computed by one fit only (its claim)
    fits = [subprocess.Popen([sys.executable, "-m", "graftcache", *fit_args(world, shared, seeds, tmp_path / "runs")],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV)
            for seeds in ("0,1", "1,2")]
    reader = subprocess.Popen([sys.executable, "-c", READER, str(shared), str(stop)], stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True, env=ENV)
    writers = [subprocess.Popen([sys.executable, "-c", WRITER, str(shared), str(k)], stderr=subprocess.PIPE,
                                text=True, env=ENV) for k in range(4)]
    try:
        for proc in writers:
            assert proc.wait(timeout=300) == 0, proc.stderr.read()[-2000:]
        outs = [proc.communicate(timeout=300) for proc in fits]
        for proc, (_, err) in zip(fits, outs):
            assert proc.returncode == 0, err[-3000:]
        stop.touch()
        reads, err = reader.communicate(timeout=60)
        assert reader.returncode == 0, err[-2000:]
        assert int(reads) > 0
    finally:  # a failed assertion must not leave the reader polling (it took the CPU from every later test)
        stop.touch()
        for proc in [*fits, reader, *writers]:
            if proc.poll() is None:
                proc.kill()
                proc.wait()

    table = results.read(shared)
    appended = table.filter(pl.col("encoder").str.starts_with("enc"))
    assert sorted(zip(appended["encoder"], appended["seed"])) == [(f"enc{k}", s) for k in range(4) for s in range(25)]
    assert appended["eval_mse"].to_list() == [float(s) for s in appended["seed"]]
    fitted = table.filter(pl.col("encoder") == ENCODER)
    assert sorted(fitted["seed"].to_list()) == [0, 1, 2] and table["run_id"].n_unique() == table.height == 103
    computed = [line.split("(cell ")[1].split(")")[0] for out, err in outs for line in (out + err).splitlines()
                if ": eval_mse " in line]  # each computed cell's one result line
    assert sorted(computed) == sorted(fitted["run_id"].to_list())  # every cell computed exactly once
    assert len(list((tmp_path / "runs").glob("*/projector.safetensors"))) == 3
    assert leftovers(tmp_path) == []


@contextmanager
def read_only_folder(path: Path) -> Iterator[Path]:
    """A folder nothing can be written into: mode 0555 for an ordinary user; root ignores modes, so for root a
    read-only tmpfs mounted over it (skipped where root may not mount)."""
    path.mkdir()
    if os.geteuid():
        path.chmod(0o555)
        try:
            yield path
        finally:
            path.chmod(0o755)
        return
    mount = subprocess.run(["mount", "-t", "tmpfs", "-o", "ro,size=1m", "tmpfs", str(path)], capture_output=True)
    if mount.returncode:
        pytest.skip(f"cannot mount a read-only tmpfs as root here: {mount.stderr.decode().strip()}")
    try:
        yield path
    finally:
        subprocess.run(["umount", str(path)], check=True)


def one_line_error(capsys: pytest.CaptureFixture) -> str:
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    return err


def test_a_row_the_results_file_cannot_take_is_kept_in_the_run_folder(world: Path, tmp_path: Path,
                                                                         capsys: pytest.CaptureFixture) -> None:
    runs = tmp_path / "runs"
    with read_only_folder(tmp_path / "ro") as ro:
        assert main(fit_args(world, ro / "results.parquet", "0", runs)) == 2
        assert list(ro.iterdir()) == []  # no temporary file, no lock
    err = one_line_error(capsys)
    (kept,) = runs.glob("*/row.parquet")
    target = ro / "results.parquet"
    assert f"{target}: cannot write the results file" in err
    assert err.endswith(f"is kept in {kept}: once {target} can be written, merge it with "
                        f"`graftcache merge-rows {kept} --results {target}`")
    row_kept = results.read(kept)
    assert row_kept.height == 1 and row_kept["seed"].to_list() == [0]
    assert (kept.parent / "projector.safetensors").is_file()
    assert kept.parent.name == row_kept["run_id"][0]
    assert leftovers(tmp_path) == []

    merged = tmp_path / "merged.parquet"
    assert main(["merge-rows", str(kept), "--results", str(merged)]) == 0
    assert main(["merge-rows", str(kept), "--results", str(merged)]) == 0  # twice: still one row
    assert results.read(merged).equals(row_kept)
    with pytest.raises(ResultsError, match="no results file at"):
        merge(merged, [tmp_path / "absent.parquet"])
    (tmp_path / "junk.parquet").write_text("not parquet")
    assert main(["merge-rows", str(tmp_path / "junk.parquet"), "--results", str(merged)]) == 2
    assert f"{tmp_path / 'junk.parquet'}: not a Parquet results table" in one_line_error(capsys)
    # the merged cell is then finished: the fit skips it
    assert main(fit_args(world, merged, "0", runs)) == 0
    assert "skip " in capsys.readouterr().out


def test_a_results_path_that_is_a_folder_is_refused_before_any_training(world: Path, tmp_path: Path,
                                                                        capsys: pytest.CaptureFixture) -> None:
    folder = tmp_path / "results.parquet"
    folder.mkdir()
    assert main(fit_args(world, folder, "0", tmp_path / "runs")) == 2
    assert one_line_error(capsys) == f"graftcache fit: error: {folder}: is a directory, not a results file; pass a " \
                                     f".parquet file"
    assert not (tmp_path / "runs").exists() and leftovers(tmp_path) == []
    with pytest.raises(ResultsError, match="is a directory"):
        results.append(folder, [row("smolvla", SUITE, "e", 0, 1.0)])


def test_a_float_seed_is_refused_not_rounded(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    path = tmp_path / "results.parquet"
    results.append(path, [row("smolvla", SUITE, "e", 0, 1.0)])
    table = pl.read_parquet(path).with_columns(pl.lit(0.5).alias("seed"))
    table.write_parquet(path)
    before = path.read_bytes()
    with pytest.raises(ResultsError, match=rf"^{path}: column seed holds 0\.5, which Int64 cannot hold unchanged"):
        results.append(path, [row("smolvla", SUITE, "e", 1, 1.0)])
    assert path.read_bytes() == before and leftovers(tmp_path) == []
    with pytest.raises(ResultsError, match="column seed holds 0.5"):
        results.done_run_ids(path)
    assert main(["report", str(path), "--out", str(tmp_path / "report")]) == 2
    assert "column seed holds 0.5" in one_line_error(capsys)
    # a row handed over with a float seed is refused too; a whole float (1.0) is the integer it names
    with pytest.raises(Exception, match="column seed holds 2.5"):
        results.append(tmp_path / "new.parquet", [row("smolvla", SUITE, "e", 2.5, 1.0)])
    results.append(tmp_path / "new.parquet", [row("smolvla", SUITE, "e", 3.0, 1.0)])
    assert results.read(tmp_path / "new.parquet")["seed"].to_list() == [3]


def _lease_file(path: Path, host: str, pid: int) -> None:
    path.write_text(json.dumps({"owner": f"{host}:{pid}:x", "host": host, "pid": pid, "since": time.time()}))


def test_a_lease_is_taken_over_only_from_a_dead_or_silent_holder(tmp_path: Path,
                                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("GRAFTCACHE_LEASE_S", "1.0")
    path = tmp_path / "x.lock"
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    _lease_file(path, socket.gethostname(), int(dead.stdout))  # this host, a pid that has exited: stale at once
    mine = FileLease(path)
    assert mine.try_acquire() and mine.holds()
    watcher = FileLease(path)
    assert not watcher.try_acquire()
    time.sleep(1.5)  # longer than the lease: only the holder's heartbeat (its mtime) keeps it
    assert not watcher.try_acquire() and mine.holds()
    mine.release()
    assert not path.exists() and not mine.holds()

    _lease_file(path, "another-host", 1)  # another machine's holder: its pid says nothing here, its heartbeat does
    other = FileLease(path)
    assert not other.try_acquire()
    time.sleep(0.2)
    assert not other.try_acquire()  # silent for less than the lease
    time.sleep(1.2)
    assert other.try_acquire() and other.holds()  # silent for longer: taken over
    other.release()
    assert leftovers(tmp_path) == []


def _recipe(tmp_path: Path, dataset: Path, shared: Path) -> Path:
    path = tmp_path / "recipe.toml"
    path.write_text(textwrap.dedent(f"""
        name = "twice"
        dataset = "{dataset}"
        results = "{shared}"
        cache = "{tmp_path / 'cache'}"
        suites = ["libero_spatial"]
        seeds = [0, 1]
        controls = ["zero-image"]
        [[backbones]]
        name = "smolvla"
        [[encoders]]
        name = "timm:vit_tiny_patch16_224"
        random_init = true
        [extract]
        batch_size = 8
        num_workers = 0
        [fit]
        steps = 2
        batch_size = 4
        num_workers = 0
        eval_frames = 4
        num_denoise_steps = 1
        [train_tiny]
        steps = 2
        batch_size = 4
    """))
    return path


@pytest.mark.slow  # ~1 min: two sweep processes (torch imports), one tiny policy, one extraction, four cells
def test_two_sweeps_of_one_recipe_compute_each_cell_once(v3_video: Written, tmp_path: Path) -> None:
    shared = tmp_path / "results.parquet"
    recipe = _recipe(tmp_path, v3_video.root, shared)
    sweeps = [subprocess.Popen([sys.executable, "-m", "graftcache", "sweep", str(recipe)],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV) for _ in range(2)]
    outs = [proc.communicate(timeout=600) for proc in sweeps]
    for proc, (_, err) in zip(sweeps, outs):
        assert proc.returncode == 0, err[-3000:]
    table = results.read(shared)
    assert table.height == 4 and sorted(table["control"]) == ["none", "none", "zero-image", "zero-image"]
    computed = [line.split("(cell ")[1].split(")")[0] for out, err in outs for line in (out + err).splitlines()
                if ": eval_mse " in line]  # each computed cell's one result line
    assert sorted(computed) == sorted(table["run_id"].to_list())  # each of the 4 cells once, over both sweeps
    logs = [out + err for out, err in outs]
    # the tiny policy is trained by one sweep and reused by the other, which waited for it
    assert sum("training tiny smolvla (train-tiny)" in log for log in logs) == 1
    assert sum("reusing tiny smolvla trained by train-tiny" in log for log in logs) == 1
    assert leftovers(tmp_path) == []


def test_a_fused_pass_whose_results_file_cannot_be_written_keeps_every_row(world: Path, tmp_path: Path,
                                                                           capsys: pytest.CaptureFixture) -> None:
    """Issue 29, items 3 and 5: a pass of three cells keeps all three rows, not only the first; the rows record
    the command line that made them (the subcommand's name used to overwrite it: `command = "fit"`)."""
    runs = tmp_path / "runs"
    args = [*fit_args(world, tmp_path / "ro" / "results.parquet", "0,1,2", runs), "--cells-per-pass", "3"]
    with read_only_folder(tmp_path / "ro") as ro:
        assert main(args) == 2
        assert list(ro.iterdir()) == []
    err = one_line_error(capsys)
    kept = sorted(runs.glob("*/row.parquet"))
    assert len(kept) == 3 and all((k.parent / "projector.safetensors").is_file() for k in kept)
    rows = pl.concat([results.read(k) for k in kept])
    assert sorted(rows["seed"]) == [0, 1, 2] and set(rows["cells_per_pass"]) == {3}
    assert set(rows["command"]) == {shlex.join(["graftcache", *args])}
    target = ro / "results.parquet"
    assert f"{target}: cannot write the results file" in err and all(str(k) in err for k in kept)
    assert "merge them with `graftcache merge-rows " in err and err.endswith(f" --results {target}`")
    merged = tmp_path / "merged.parquet"
    assert main(["merge-rows", *map(str, kept), "--results", str(merged)]) == 0
    assert sorted(results.read(merged)["seed"]) == [0, 1, 2] and leftovers(tmp_path) == []


def test_a_read_only_results_folder_without_out_keeps_the_cells_work(world: Path, tmp_path: Path,
                                                                     capsys: pytest.CaptureFixture) -> None:
    """Issue 29, item 7: with no --out, the run folders beside an unwritable results file fall back to runs/ in
    the local cache folder, said in the log, instead of the projector save failing and losing the cell."""
    cache = tmp_path / "cache"
    shutil.copytree(world / "cache", cache)
    args = fit_args(world, tmp_path / "ro" / "results.parquet", "0", tmp_path / "unused")
    args = [*args[:args.index("--out")], *args[args.index("--out") + 2:]]
    args[args.index("--cache") + 1] = str(cache)
    with read_only_folder(tmp_path / "ro"):
        assert main(args) == 2
    captured = capsys.readouterr()
    (kept,) = (cache / "runs").glob("*/row.parquet")
    assert (kept.parent / "projector.safetensors").is_file() and results.read(kept)["seed"].to_list() == [0]
    assert f"are kept in {cache / 'runs'}" in captured.out
    assert f"is kept in {kept}: once" in captured.err and len(captured.err.strip().splitlines()) == 1


def test_merging_rows_twice_or_a_copy_of_them_adds_nothing(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """Issue 29, item 2: `merge-rows A A`, or A and a copy of A, appended every row twice."""
    rows, merged = tmp_path / "a.parquet", tmp_path / "merged.parquet"
    results.append(rows, [row("smolvla", SUITE, "e", seed, 1.0 + seed) for seed in (0, 1)])
    shutil.copy(rows, tmp_path / "copy.parquet")
    assert main(["merge-rows", str(rows), str(rows), "--results", str(merged)]) == 0
    once = results.read(merged)
    assert once.height == 2 and once["run_id"].n_unique() == 2
    assert "merged 2 row(s)" in capsys.readouterr().out
    assert main(["merge-rows", str(rows), str(tmp_path / "copy.parquet"), "--results", str(merged)]) == 0
    assert results.read(merged).equals(once)
    assert ": 0 new, 2 replacing" in capsys.readouterr().out
    assert results.read_for_report(merged).height == 2


def test_a_writer_waiting_for_a_lock_says_for_what_and_on_whom(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Issue 29, item 6: a stale, empty or other machine's lock made a writer wait the lease out without a word.
    The writer says so after graftcache.results.writing.WAIT_TOLD_S (1 s) of waiting and takes the lease over after its
    3 s: with a lease of 1.5 s, one stall of half a second on a loaded machine took it over before a word (seen once
    in CI)."""
    monkeypatch.setenv("GRAFTCACHE_LEASE_S", "3")
    path = tmp_path / "results.parquet"
    lock = lock_path(path)
    for holder, named in ((lambda: _lease_file(lock, "another-host", 1), "another-host pid 1 since"),
                          (lambda: lock.write_bytes(b""), "an empty or unreadable lock file")):
        holder()
        said: list[str] = []
        results.append(path, [row("smolvla", SUITE, "e", 0, 1.0)], log=said.append)
        assert len(said) == 1 and said[0].startswith(f"waiting for {lock} (the lock of {path}), held by ")
        assert named in said[0] and "silent for 3 s, is taken over" in said[0]
    said = []
    results.append(path, [row("smolvla", SUITE, "e", 1, 1.0)], log=said.append)
    assert said == [] and leftovers(tmp_path) == []  # a free lock: nothing said


def test_a_directory_at_the_locks_path_is_named_as_such(tmp_path: Path) -> None:
    """Issue 29, item 6: it was reported as "cannot write the results file (Is a directory)"."""
    path = tmp_path / "results.parquet"
    lock_path(path).mkdir()
    with pytest.raises(ResultsError) as refused:
        results.append(path, [row("smolvla", SUITE, "e", 0, 1.0)])
    assert str(refused.value) == (f"{lock_path(path)}: is a directory, where the writers of {path} keep "
                                  "their lock file; remove it")
    assert not path.exists()


def test_a_results_path_that_is_a_link_is_followed(tmp_path: Path) -> None:
    """Issue 29, item 6: the link used to be replaced by a regular file. It is followed: the file it points to is
    replaced, the link stays, and the lock and claims are beside the file (writers through other links share them)."""
    real, link = tmp_path / "shared" / "results.parquet", tmp_path / "mine.parquet"
    real.parent.mkdir()
    link.symlink_to(real)
    results.append(link, [row("smolvla", SUITE, "e", 0, 1.0)])
    results.append(real, [row("smolvla", SUITE, "e", 1, 1.0)])
    assert link.is_symlink() and link.resolve() == real
    assert sorted(results.read(link)["seed"]) == [0, 1] == sorted(results.read(real)["seed"])
    assert claims_folder(link) == claims_folder(real)
    assert sorted(p.name for p in tmp_path.rglob("*")) == ["mine.parquet", "results.parquet", "shared"]


def test_claims_are_given_back_whatever_interrupts_them(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Issue 29, item 6: Ctrl-C left claim files of finished cells and an empty claims folder. A claim is given
    back when the interrupt lands while it is taken or while another is given back, and the folder goes once empty."""
    path = tmp_path / "results.parquet"
    claims = [cell_claim(path, f"cell{i}") for i in range(3)]
    assert all(c.try_acquire() for c in claims)
    release = claims[0].release
    monkeypatch.setattr(claims[0], "release", lambda: (release(), _raise(KeyboardInterrupt())))
    with pytest.raises(KeyboardInterrupt):
        release_all(claims)
    assert list(claims_folder(path).iterdir()) == []
    drop_claims_folder(path)
    assert list(tmp_path.iterdir()) == []

    late = cell_claim(path, "late")
    monkeypatch.setattr(threading.Thread, "start", lambda self: _raise(KeyboardInterrupt()))
    with pytest.raises(KeyboardInterrupt):
        late.try_acquire()  # interrupted after its file was made, before the caller knew it held the claim
    monkeypatch.undo()
    assert list(claims_folder(path).iterdir()) == []


def _raise(e: BaseException) -> None:
    raise e


def test_a_fit_leaves_no_claims_folder(world: Path, tmp_path: Path) -> None:
    assert main(fit_args(world, tmp_path / "results.parquet", "0", tmp_path / "runs")) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["results.parquet", "runs"]
