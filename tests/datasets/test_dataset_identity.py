"""A dataset's identity covers its data, not only its metadata files (issue 15).

One changed byte in a video, a data parquet or a metadata file changes the cache key; touching a file
does not; the hashes are remembered so a rerun on the bundled sample hashes nothing; hub
hashes stand in for hashing; a cache whose recorded dataset differs from the dataset it is used with is
refused naming the first differing file; the NaN-edited copy of the sample gets its own cache.
"""

from __future__ import annotations

import json
import os
import shutil
import time
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from helpers.caches import manifest
from helpers.requests import extract_request

from graftcache.datasets import identity, open_dataset
from graftcache.errors import CacheError, DatasetError
from graftcache.store import cache_key, compare_identity

SAMPLE = Path(__file__).resolve().parents[2] / "data" / "libero_sample"
DATA = "data/chunk-000/file-000.parquet"
VIDEO = "videos/observation.images.image/chunk-000/file-000.mp4"
INFO = "meta/info.json"
ENCODER = "timm:vit_tiny_patch16_224"


@pytest.fixture
def memo(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A fresh, private hash sidecar folder per test."""
    folder = tmp_path / "memo"
    monkeypatch.setenv(identity.MEMO_ENV, str(folder))
    return folder


@pytest.fixture
def sample(tmp_path: Path) -> Path:
    root = tmp_path / "libero_sample"
    shutil.copytree(SAMPLE, root)
    return root


def _identity_of(root: Path | str, stats: identity.HashStats | None = None) -> dict:
    """A dataset's identity as a cache records it; `stats`, when given, says what computing it did."""
    meta = open_dataset(root).meta
    if stats is None:
        return {"codebase_version": meta.codebase_version, **meta.content_identity}
    return {"codebase_version": meta.codebase_version,
            **identity.content_identity(meta.root, meta.identity_files, stats=stats)}


def _key(dataset_identity: dict) -> str:
    """The cache key of a fixed extraction request on a dataset with this identity."""
    return cache_key(manifest(dataset_identity=dataset_identity, encoder={"name": "toy"}).to_dict())


def _flip_byte(path: Path, offset: int) -> None:
    data = bytearray(path.read_bytes())
    data[offset] ^= 0x01
    path.write_bytes(bytes(data))


def _nan_episode(path: Path, episode: int) -> None:
    """Write NaN into the state and action of one episode, as pyarrow would for any edit of the data."""
    table = pq.read_table(path)
    hit = table.column("episode_index").to_numpy() == episode
    for name in ("observation.state", "action"):
        col = table.column(name)
        values = np.stack(col.to_pylist()).astype(np.float32)
        values[hit] = np.nan
        arr = pa.FixedSizeListArray.from_arrays(pa.array(values.reshape(-1)), values.shape[1])
        table = table.set_column(table.schema.get_field_index(name), pa.field(name, col.type), arr)
    pq.write_table(table, path, row_group_size=64)


# ------------------------------------------------------------------------------------------ what it covers
def test_identity_covers_metadata_data_and_videos(sample: Path, memo: Path) -> None:
    files = _identity_of(sample)["files"]
    assert set(files) == {INFO, "meta/tasks.parquet", "meta/episodes/chunk-000/file-000.parquet", DATA, VIDEO,
                          "videos/observation.images.image2/chunk-000/file-000.mp4"}
    for rel, entry in files.items():
        data = (sample / rel).read_bytes()
        assert entry == {"size": len(data), "sha256": identity.sha256_file(sample / rel)}, rel


@pytest.mark.parametrize("rel, offset", [(VIDEO, 400_000), (DATA, 100_000), (INFO, None)],
                         ids=["video", "data-parquet", "metadata"])
def test_one_changed_byte_changes_the_key(sample: Path, memo: Path, rel: str, offset: int | None) -> None:
    before = _identity_of(sample)
    path = sample / rel
    if offset is None:  # keep info.json valid JSON: one byte of a string value
        text = path.read_bytes()
        assert text.count(b'"panda"') == 1
        path.write_bytes(text.replace(b'"panda"', b'"pandA"'))
    else:
        _flip_byte(path, offset)
    after = _identity_of(sample)
    assert _key(after) != _key(before)
    diff = compare_identity(before, after)
    assert diff is not None and diff.path == rel and "sha256" in diff.detail
    assert str(diff).startswith(rel)


def test_changed_byte_is_seen_even_with_the_mtime_put_back(sample: Path, memo: Path) -> None:
    before = _identity_of(sample)
    path = sample / DATA
    st = path.stat()
    _flip_byte(path, 50_000)
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns))  # same size, same mtime, other bytes
    assert compare_identity(before, _identity_of(sample)).path == DATA


def test_touching_a_file_changes_nothing(sample: Path, memo: Path) -> None:
    before = _identity_of(sample)
    for rel in (VIDEO, DATA, INFO):
        later = time.time() + 3600
        os.utime(sample / rel, (later, later))
    assert _identity_of(sample) == before


def test_a_rerun_reuses_the_remembered_hashes(sample: Path, memo: Path) -> None:
    first_stats, stats = identity.HashStats(), identity.HashStats()
    first = _identity_of(sample, first_stats)
    assert first_stats.hashed_files == 6 and first_stats.hashed_bytes > 14e6
    again = _identity_of(sample, stats)  # a new DatasetMeta: only the sidecar can make this cheap
    assert again == first and stats.hashed_files == 0 and stats.hashed_bytes == 0 and stats.from_memo == 6


def test_an_unwritable_sidecar_only_costs_time(sample: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    blocker = tmp_path / "not-a-folder"
    blocker.write_text("x")
    monkeypatch.setenv(identity.MEMO_ENV, str(blocker / "memo"))
    first, stats = _identity_of(sample), identity.HashStats()
    assert _identity_of(sample, stats) == first and stats.hashed_files == 6


def test_a_shared_home_not_writable_falls_back_to_the_user_cache(sample: Path, tmp_path: Path,
                                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    shared = tmp_path / "shared"
    shared.mkdir()
    (shared / identity.MEMO_DIR).write_text("not a folder: stands for another user's read-only one")
    monkeypatch.delenv(identity.MEMO_ENV, raising=False)
    monkeypatch.setenv("GRAFTCACHE_HOME", str(shared))
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    first = _identity_of(sample)
    assert len(list((tmp_path / "xdg" / "graftcache" / identity.MEMO_DIR).glob("*.json"))) == 1
    stats = identity.HashStats()
    assert _identity_of(sample, stats) == first and stats.hashed_files == 0


def test_a_missing_data_file_is_named(sample: Path, memo: Path) -> None:
    (sample / VIDEO).unlink()
    meta = open_dataset(sample).meta  # opening still works; the identity needs every file
    with pytest.raises(DatasetError, match=f"{sample / VIDEO}: missing"):
        _ = meta.content_identity


# ------------------------------------------------------------------------------------------ hub stand-ins
def test_hub_snapshot_blob_names_stand_in_for_hashing(sample: Path, memo: Path, tmp_path: Path,
                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    plain = _identity_of(sample)
    hub = tmp_path / "hub"
    repo = hub / "datasets--org--sample"
    rev = "0123456789abcdef0123456789abcdef01234567"
    for rel, entry in plain["files"].items():
        # LFS files are stored under their sha256; small git files (info.json) under a 40-hex git oid
        oid = entry["sha256"] if rel != INFO else "f" * 40
        blob = repo / "blobs" / oid
        blob.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(sample / rel, blob)
        link = repo / "snapshots" / rev / rel
        link.parent.mkdir(parents=True, exist_ok=True)
        link.symlink_to(os.path.relpath(blob, link.parent))
    (repo / "refs").mkdir()
    (repo / "refs" / "main").write_text(rev)
    monkeypatch.setenv("HF_HUB_CACHE", str(hub))
    stats = identity.HashStats()
    assert _identity_of("org/sample", stats) == plain  # same identity as a plain copy: caches are shared
    assert stats.from_hub == 5 and stats.hashed_files == 1  # only info.json was read


def test_local_dir_download_metadata_stands_in_while_fresh(sample: Path, memo: Path) -> None:
    plain = _identity_of(sample)
    sha = plain["files"][DATA]["sha256"]
    meta_file = sample / ".cache" / "huggingface" / "download" / f"{DATA}.metadata"
    meta_file.parent.mkdir(parents=True)
    meta_file.write_text(f"{'a' * 40}\n{sha}\n{time.time() + 5:.3f}\n")
    shutil.rmtree(memo)
    stats = identity.HashStats()
    assert _identity_of(sample, stats) == plain and stats.from_hub == 1
    # edited after the download: huggingface_hub's freshness rule no longer holds, so it is hashed
    _flip_byte(sample / DATA, 1000)
    later = time.time() + 60
    os.utime(sample / DATA, (later, later))
    now = _identity_of(sample)
    assert now["files"][DATA]["sha256"] == identity.sha256_file(sample / DATA) != sha


# ------------------------------------------------------------------------------------------ comparing
def test_compare_identity_names_the_first_differing_file() -> None:
    def ident(**files: str) -> dict:
        return {"codebase_version": "v3.0",
                "files": {k.replace("__", "/"): {"size": 1, "sha256": v} for k, v in files.items()}}

    a = ident(meta__info="1", data__a="2", videos__v="3")
    assert compare_identity(a, json.loads(json.dumps(a))) is None
    d = compare_identity(a, ident(meta__info="9", data__a="9", videos__v="3"))
    assert d.path == "meta/info"  # metadata first
    assert compare_identity(a, ident(meta__info="1", data__a="2")).path == "videos/v"
    assert "not recorded" in compare_identity(a, ident(meta__info="1", data__a="2", videos__v="3",
                                                          videos__w="4")).detail
    sized = {"codebase_version": "v3.0", "files": {"data/a": {"size": 2, "sha256": "2"}}}
    assert "size 1 recorded, 2 now" in str(compare_identity(ident(data__a="2"), sized))
    assert compare_identity(a, {**a, "codebase_version": "v2.1"}).path == "codebase_version"


# ------------------------------------------------------------------------------------------ caches
def _extract(dataset: Path, cache: Path, log: list[str], allow_nonfinite: bool = False):
    from graftcache.extract import extract

    req = extract_request(dataset, cache, encoder=ENCODER, grids=("2x2",), episodes=(0,), cameras=("image",), seed=0,
                          batch_size=16, allow_nonfinite=allow_nonfinite)
    return extract(req, log=log.append)


def test_nan_edited_copy_gets_its_own_cache_and_stale_caches_are_refused(
        sample: Path, memo: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import graftcache.extract
    from graftcache.errors import FitError
    from graftcache.fit.lookup import find_cache

    cache = tmp_path / "caches"
    log: list[str] = []
    clean = _extract(sample, cache, log)
    assert not clean.reused
    # the probe: NaN in one episode's state/action, meta/ untouched
    meta_before = {p: p.read_bytes() for p in (sample / "meta").rglob("*") if p.is_file()}
    _nan_episode(sample / DATA, 0)
    assert {p: p.read_bytes() for p in (sample / "meta").rglob("*") if p.is_file()} == meta_before

    # fit --dataset on the edited folder: the clean cache of this folder is refused, naming the file
    with pytest.raises(FitError, match=f"first differing file: {DATA}") as err:
        find_cache(cache, ENCODER, dataset=str(sample))
    assert len(str(err.value).splitlines()) == 1 and clean.key in str(err.value)

    # a cache under a key it does not belong to (copied, or pulled) is never reused or resumed
    with monkeypatch.context() as mp:
        mp.setattr(graftcache.extract, "cache_key", lambda manifest: clean.key)
        with pytest.raises(CacheError, match=f"first differing file: {DATA}"):
            _extract(sample, cache, log, allow_nonfinite=True)

    # the NaNs themselves are refused by default, naming episode and frame; --allow-nonfinite caches them
    with pytest.raises(DatasetError, match="episode 0 frame 0: state"):
        _extract(sample, cache, log)
    log.clear()
    edited = _extract(sample, cache, log, allow_nonfinite=True)
    assert edited.key != clean.key and not edited.reused and edited.frames_encoded > 0
    assert not any("reusing complete cache" in line for line in log)
    from graftcache.store import FeatureCache

    got = FeatureCache(edited.path).index()
    assert np.isnan(np.stack(got["state"].to_list())).all()  # the edited numbers, not the clean cache's
    assert find_cache(cache, ENCODER, dataset=str(sample)).key == edited.key  # the stale one is passed over
    with pytest.raises(FitError, match=f"first differing file: {DATA}"):
        find_cache(cache, ENCODER, dataset=str(sample), key=clean.key)
