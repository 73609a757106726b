"""Caches and results files of previous formats (1 and 2) go through one upgrade path each: a format 2 cache, and
a format 1 cache that records everything format 2 does, is read as format 3 (its keys renamed as
store.manifest.RENAMED declares); a format 1 cache made before graftcache recorded frame strides, unpooled grids,
numerics fingerprints or content identities is refused in one line naming the cache and the command that
rebuilds it; a results file of format 1 or 2 (run_ids of cells of another shape) is refused in one line naming
the command that wrote it; one of format 3 or 4 is read as this format, and its rows' cells are still exported."""

from __future__ import annotations

import dataclasses
import hashlib
import json
from pathlib import Path

import polars as pl
import pytest
from helpers.caches import CAMERAS, synthetic_cache
from helpers.previous_formats import previous_format, previous_results
from helpers.tables import row, table

from graftcache import results
from graftcache.cli import main
from graftcache.errors import CacheError, ExportError, ResultsError
from graftcache.export.bundle import cell_of
from graftcache.fit.plan import Cell
from graftcache.fit.run import PROJECTOR_SIDECAR
from graftcache.results.schema import CELL_COLUMNS, make_policy_id
from graftcache.store import FORMAT_VERSION, BrokenCache, FeatureCache, list_caches, scan_caches
from graftcache.store.manifest import PREVIOUS_GAPS, RENAMED

REBUILD = ("graftcache extract --encoder synthetic --dataset synthetic --random-init --seed 0 --grids 4x4 "
           "--cameras image,image2 --storage-dtype fp16 --compute-dtype fp32")


@pytest.fixture(scope="module")
def made(tmp_path_factory: pytest.TempPathFactory) -> FeatureCache:
    return synthetic_cache(tmp_path_factory.mktemp("formats"), (5, 7), block_frames=4)


@pytest.mark.parametrize("version", [1, 2])
def test_a_previous_format_cache_recording_everything_is_read_as_this_format(made: FeatureCache, tmp_path: Path,
                                                                              version: int) -> None:
    path = previous_format(made.path, tmp_path, version=version)
    stored = json.loads((path / "zarr.json").read_text())["attributes"]["manifest"]
    assert stored["format_version"] == version and not set(RENAMED.values()) & set(stored)  # the former names
    old = FeatureCache(path)
    assert old.key != made.key  # its folder is named by what it stores, in its format
    assert old.manifest == made.manifest and old.manifest.format_version == FORMAT_VERSION == 3
    for camera in CAMERAS:
        assert old.read_features(camera, "4x4").equal(made.read_features(camera, "4x4"))
    assert [c.key for c in list_caches(tmp_path)] == [old.key]


@pytest.mark.parametrize(("lacking", "what"), PREVIOUS_GAPS)
def test_a_previous_format_cache_made_before_a_record_is_refused_in_one_line(
        made: FeatureCache, tmp_path: Path, capsys: pytest.CaptureFixture, lacking: str, what: str) -> None:
    path = previous_format(made.path, tmp_path, lacking)
    line = (f"cache {path.name} ({path}): it was made before graftcache recorded {what} (format 1); graftcache "
            f"reads caches of format 3 and the format 1 and 2 caches made since; rebuild it: {REBUILD}")
    with pytest.raises(CacheError) as refused:
        FeatureCache(path)
    assert str(refused.value) == line
    assert main(["info", path.name, "--cache", str(tmp_path)]) == 2
    assert capsys.readouterr().err == f"graftcache info: error: {line}\n"
    assert scan_caches(tmp_path) == ([], [BrokenCache(path.name, line)])  # what `ls` lists as broken


@pytest.mark.parametrize("version", [1, 2])
def test_a_previous_format_results_file_is_refused_in_one_line(tmp_path: Path, capsys: pytest.CaptureFixture,
                                                                version: int) -> None:
    old = tmp_path / "old.parquet"
    rows = table([row("smolvla", "libero_spatial", "siglip", seed, 0.5) for seed in (0, 1)])
    previous_results(old, rows, version)
    command = rows["command"][0]
    line = (f"{old}: 2 row(s) of an older results format than 3 (run_ids of cells of another shape); move the "
            f"file aside and rebuild it: `{command}` (and 1 other command(s) its rows record)")
    with pytest.raises(ResultsError) as refused:
        results.read(old)
    assert str(refused.value) == line
    kept = tmp_path / "kept.parquet"
    table([row("smolvla", "libero_spatial", "siglip", 2, 0.4)]).write_parquet(kept)
    assert main(["merge-rows", str(kept), "--results", str(old)]) == 2
    assert capsys.readouterr().err == f"graftcache merge-rows: error: {line}\n"
    assert results.read(kept)["format_version"].to_list() == [results.FORMAT_VERSION]  # read as they are


def test_format_3_rows_are_read_as_this_format_with_their_run_ids(tmp_path: Path) -> None:
    """Format 4 added columns and a cell field hashed only off its default (issue 31): a format 3 row names its cell
    by the run_id format 4 gives it, so it is upgraded, not refused: split the graftcache way, arm and gripper
    MSEs null (not measured then), and appending to it rewrites the file as this format."""
    old = tmp_path / "old.parquet"
    rows = table([row("smolvla", "libero_spatial", "siglip", seed, 0.5) for seed in (0, 1)])
    previous_results(old, rows, 3)
    assert "eval_split" not in pl.read_parquet(old).columns
    read = results.read(old)
    assert read["run_id"].to_list() == rows["run_id"].to_list()
    assert read["format_version"].to_list() == [7, 7] and read["eval_split"].to_list() == ["graftcache"] * 2
    assert read["eval_mse_arm"].null_count() == read["eval_mse_gripper"].null_count() == 2
    # random_init is the union of the encoder's and the backbone's: false says both were false
    assert read["encoder_random_init"].to_list() == read["backbone_random_init"].to_list() == [False, False]
    results.append(old, table([row("smolvla", "libero_spatial", "siglip", 2, 0.4, eval_split="graftcache")]))
    assert pl.read_parquet(old)["format_version"].to_list() == [7, 7, 7]


def test_format_4_rows_from_before_the_random_init_split_are_read_with_what_random_init_says(tmp_path: Path) -> None:
    """Issue 32 split random_init into the encoder's and the backbone's within format 4: rows written before lack
    the two columns, and get false where random_init says both were false, else null (which of the two was
    random-init is unknown); their run_ids stand."""
    old = tmp_path / "old.parquet"
    rows = table([row("smolvla", "libero_spatial", "siglip", seed, 0.5, random_init=seed == 1) for seed in (0, 1)])
    previous_results(old, rows.drop("encoder_random_init", "backbone_random_init"), 4)
    read = results.read(old)
    assert read["run_id"].to_list() == rows["run_id"].to_list() and read["format_version"].to_list() == [7, 7]
    assert read["encoder_random_init"].to_list() == read["backbone_random_init"].to_list() == [False, None]
    assert read["random_init"].to_list() == [False, True]



def test_an_older_results_file_whose_rows_name_no_command_line_is_refused_without_one(tmp_path: Path) -> None:
    """Issue 29, item 5: rows written by `graftcache fit` before it recorded its command line say `fit`, which the
    refusal offered as the command that rebuilds the file."""
    old = previous_results(tmp_path / "old.parquet", table([row("smolvla", "libero_spatial", "siglip", 0, 0.5,
                                                                 command="fit")]), 2)
    with pytest.raises(ResultsError) as refused:
        results.read(old)
    assert str(refused.value).endswith("move the file aside and rebuild it: the fits or sweeps that wrote them (its "
                                       "rows record no command line)")


def test_a_newer_results_file_is_called_newer(tmp_path: Path) -> None:
    newer = previous_results(tmp_path / "newer.parquet", table([row("smolvla", "libero_spatial", "siglip", 0, 0.5)]),
                             results.FORMAT_VERSION + 1)
    with pytest.raises(ResultsError) as refused:
        results.read(newer)
    assert str(refused.value).startswith(f"{newer}: 1 row(s) of results format 8, newer than this graftcache's (7, ")
    assert "older" not in str(refused.value)


def test_a_foreign_parquet_file_is_called_foreign(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    foreign = tmp_path / "prices.parquet"
    pl.DataFrame({"item": ["a"], "price": [1.0]}).write_parquet(foreign)
    line = (f"{foreign}: not a graftcache results table (no column run_id, backbone, suite, encoder, control, seed, "
            "eval_mse); pass another --results")
    with pytest.raises(ResultsError) as refused:
        results.read(foreign)
    assert str(refused.value) == line
    assert main(["merge-rows", str(foreign), "--results", str(tmp_path / "r.parquet")]) == 2
    assert capsys.readouterr().err == f"graftcache merge-rows: error: {line}\n"


def _cell_row(cell: Cell) -> dict:
    """The results row of `cell`, its measurements made up (camera names matched: rows spell the mapping out)."""
    fields = {k: v for k, v in dataclasses.asdict(cell).items() if k not in ("backbone", "suite", "seed")}
    return row(cell.backbone, cell.suite, "smolvla-native", cell.seed, 1.0,
               **{**fields, "camera_map": "image=image,image2=image2"}, run_id=cell.run_id)


NATIVE = Cell(backbone="smolvla", policy="tiny", cache_key="smolvla-native-00aa", suite="libero_spatial", seed=0,
              control="native", pool_grid="4x4", objective="eval", steps=0, lr=0.0, batch_size=0, buffer_mib=0,
              lora_rank=0, eval_fraction=0.2, eval_split_seed=0, eval_frames=None, num_denoise_steps=None,
              compute_dtype="fp32")


def test_format_4_rows_lack_part_of_their_cell_and_are_still_exported(tmp_path: Path) -> None:
    """Issue 41, item 3: format 5 records every cell field; a format 4 row keeps its run_id and reads with lora_rank 0
    (not the lora control) and the other added fields null. Its cell is then its run folder's (the sidecar of a
    graftcache before issue 41 recorded the identity's version as a field), or, for a cell that trained nothing,
    the row's with the unrecorded fields at their defaults, where that gives its run_id; else one line says so."""
    lora = dataclasses.replace(NATIVE, control="lora", objective="flow", steps=5, lr=0.01, batch_size=4,
                               buffer_mib=64, lora_rank=16, eval_fraction=0.3, num_denoise_steps=2,
                               cache_key="siglip-00aa")
    odd = dataclasses.replace(NATIVE, eval_fraction=0.3, seed=1)
    rows = table([_cell_row(c) for c in (NATIVE, lora, odd)])
    old = previous_results(tmp_path / "old.parquet", rows, 4)
    read = results.read(old)
    assert read["run_id"].to_list() == [NATIVE.run_id, lora.run_id, odd.run_id]
    assert read["format_version"].to_list() == [7] * 3 and read["lora_rank"].to_list() == [0, None, 0]
    assert read["eval_fraction"].null_count() == 3
    native_row, lora_row, odd_row = read.iter_rows(named=True)
    assert cell_of(native_row, None) == NATIVE
    folder = tmp_path / "runs" / lora.run_id
    folder.mkdir(parents=True)
    (folder / PROJECTOR_SIDECAR).write_text(json.dumps({"run_id": lora.run_id, "cell": {
        **dataclasses.asdict(lora), "format_version": 3}}))
    assert cell_of(lora_row, folder) == lora
    with pytest.raises(ExportError, match=f"run {odd.run_id}: its row does not record its whole cell .*eval_fraction"):
        cell_of(odd_row, None)
    this = table([_cell_row(c) for c in (NATIVE, lora, odd)])  # as this format writes them: each cell whole
    assert [cell_of(r, None) for r in this.iter_rows(named=True)] == [NATIVE, lora, odd]



def _hand_policy_id(fields: dict) -> str:
    """sha256 of the canonical JSON of `fields` with the policy identity's version, by hand."""
    text = json.dumps({**fields, "policy_identity": 1}, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def test_format_5_rows_get_the_policy_id_their_cells_give(tmp_path: Path) -> None:
    """Format 6 added policy_id: a format 5 row keeps its run_id and gets the hash of the cell it records, less its
    seed where it trained nothing (native: one policy over seeds, as graftcache.fit.controls declares for new rows);
    a zero-image row of then keeps its cache_key (its projector started from a random init drawn at the encoder's
    width), and every trained row its seed."""
    native_1 = dataclasses.replace(NATIVE, seed=1)
    zero = [dataclasses.replace(NATIVE, control="zero-image", objective="flow", steps=5, lr=0.01, batch_size=4,
                                buffer_mib=64, cache_key=key) for key in ("siglip-00aa", "dinov2-00bb")]
    cells = (NATIVE, native_1, *zero)
    old = previous_results(tmp_path / "old.parquet", table([_cell_row(c) for c in cells]), 5)
    assert "policy_id" not in pl.read_parquet(old).columns
    read = results.read(old)
    assert read["run_id"].to_list() == [c.run_id for c in cells]
    without_seed = {k: v for k, v in dataclasses.asdict(NATIVE).items() if k != "seed"}
    assert read["policy_id"].to_list() == [_hand_policy_id(without_seed)] * 2 + [
        _hand_policy_id(dataclasses.asdict(c)) for c in zero]
    assert read["policy_id"].n_unique() == 3
    assert _hand_policy_id(without_seed) == make_policy_id(without_seed)
    # a file of both formats: the format 6 row's policy_id is kept as written
    results.append(old, table([{**_cell_row(dataclasses.replace(NATIVE, seed=2)), "policy_id": "f" * 16}]))
    assert results.read(old)["policy_id"].to_list()[-1] == "f" * 16
    assert pl.read_parquet(old)["format_version"].unique().to_list() == [results.FORMAT_VERSION]


def test_every_cell_field_is_a_cell_column_policy_ids_are_computed_from() -> None:
    assert set(CELL_COLUMNS) == {f.name for f in dataclasses.fields(Cell)}


def test_format_6_rows_are_read_with_their_kernels_unknown(tmp_path: Path) -> None:
    """Format 7 added `kernels`, what a row's numbers depend on beyond its cell: a format 6 row keeps its run_id and
    policy_id, and its kernels are unknown (null), not the reading machine's."""
    rows = table([row("smolvla", "libero_spatial", "siglip", seed, 0.5) for seed in (0, 1)])
    old = previous_results(tmp_path / "old.parquet", rows, 6)
    assert "kernels" not in pl.read_parquet(old).columns
    read = results.read(old)
    assert read["run_id"].to_list() == rows["run_id"].to_list()
    assert read["policy_id"].to_list() == rows["policy_id"].to_list()
    assert read["format_version"].to_list() == [7, 7] and read["kernels"].to_list() == [None, None]
