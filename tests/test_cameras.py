"""Cameras are matched by name, or mapped explicitly, never by position (graftcache/cameras.py).

The dataset here is what lerobot 0.6 conversions of LIBERO look like: cameras `agentview` / `eye_in_hand`,
against a tiny policy trained on `image` / `image2`. Its frames, states and actions are those of the
`v3_image` fixture (the same writer, camera by camera), so a fit fed through a map must reproduce, number for
number, the by-name fit on `v3_image`: an independent check that the map feeds each slot the camera it names.
"""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any

import pytest
from helpers.datasets import Written, build_lerobot
from helpers.world import World

from graftcache import results
from graftcache.backbones import get_backbone
from graftcache.cli import main
from graftcache.errors import GraftcacheError
from graftcache.recipe import RecipeError, load_recipe
from graftcache.store import list_caches
from graftcache.sweep import run_sweep

ENCODER = "timm:vit_tiny_patch16_224"
CAMERAS = ("observation.images.agentview", "observation.images.eye_in_hand")
MAP = "image=agentview,image2=eye_in_hand"
SWAPPED = "image=eye_in_hand,image2=agentview"
BOTH_SIDES = ("image, image2", "agentview, eye_in_hand")


@pytest.fixture(scope="module")
def world(tmp_path_factory: pytest.TempPathFactory, v3_image: Written) -> World:
    """The agentview/eye_in_hand dataset, a tiny smolvla on image/image2, and one encoder cache of each dataset
    (`v3_image`: the same frames under the policy's camera names)."""
    dataset = build_lerobot(tmp_path_factory, "agentview", video=False, cameras=CAMERAS)
    return World(tmp_path_factory.mktemp("cameras"), dataset, encoder=ENCODER, extract_settings={"batch_size": 8},
                 others=(v3_image,), fit={"steps": 2, "eval_frames": 4, "num_denoise_steps": 2})


def fit(world: World, results_path: Path, *extra: str, **given: Any) -> int:
    """`graftcache fit` of the world's smolvla; `given`: another dataset, policy or cache than the world's."""
    return main(world.fit_argv(results_path, *extra, **given))


def _one_error_line(capsys: pytest.CaptureFixture) -> str:
    err = capsys.readouterr().err.strip()
    assert "Traceback" not in err and len(err.splitlines()) == 1, err
    return err


def test_fit_refuses_differing_names_naming_both_sides(world: World, tmp_path: Path,
                                                       capsys: pytest.CaptureFixture) -> None:
    out = tmp_path / "r.parquet"
    assert fit(world, out) == 2
    err = _one_error_line(capsys)
    assert all(side in err for side in BOTH_SIDES) and "--camera-map" in err and str(world.policy) in err
    assert not out.exists()


def test_a_map_feeds_each_slot_the_camera_it_names_and_rows_record_it(world: World, tmp_path: Path,
                                                                      capsys: pytest.CaptureFixture) -> None:
    mapped, swapped, by_name = (tmp_path / f"{n}.parquet" for n in ("mapped", "swapped", "by_name"))
    assert fit(world, mapped, "--camera-map", " image2 = eye_in_hand , image=agentview") == 0  # any order, spaces
    assert fit(world, swapped, "--camera-map", SWAPPED) == 0
    assert fit(world, by_name, dataset=world.others[0]) == 0
    assert f"cameras mapped as asked (policy=cache): {MAP}" in capsys.readouterr().out
    m, s, n = (results.read(p).row(0, named=True) for p in (mapped, swapped, by_name))
    assert (m["camera_map"], s["camera_map"], n["camera_map"]) == (MAP, SWAPPED, "image=image,image2=image2")
    # agentview/eye_in_hand hold v3_image's image/image2 frames: the mapped fit is the by-name fit, to the bit
    assert (m["eval_mse"], m["train_loss_final"]) == (n["eval_mse"], n["train_loss_final"])
    assert s["eval_mse"] != m["eval_mse"]  # the other map feeds the slots the other way round
    assert s["cache_key"] == m["cache_key"] and s["run_id"] != m["run_id"]  # so it is another row
    assert fit(world, mapped, "--camera-map", MAP) == 0  # the same map is the same row: skipped
    assert "already in" in capsys.readouterr().out and results.read(mapped).height == 1


@pytest.mark.parametrize(("camera_map", "says"), [
    ("image=agentview,image2=agentview", "cache camera 'agentview' would feed policy cameras image, image2"),
    ("image=agentview,image=eye_in_hand", "policy camera 'image' is mapped twice"),
    ("image=agentview", "leaves policy camera(s) image2 unmapped"),
    ("image=agentview,wrist=eye_in_hand", "names policy camera 'wrist', which the policy lacks"),
    ("image=agentview,image2=wrist_image", "names camera 'wrist_image', which cache"),
    ("image:agentview", "is not POLICY=CACHE"),
])
def test_ambiguous_or_unknown_maps_are_one_line_errors(world: World, tmp_path: Path, capsys: pytest.CaptureFixture,
                                                       camera_map: str, says: str) -> None:
    out = tmp_path / "r.parquet"
    try:
        code = fit(world, out, "--camera-map", camera_map)
    except SystemExit as e:  # argparse's usage error for a map that cannot be right whatever the cameras
        code = e.code
    assert code == 2 and not out.exists()
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert "Traceback" not in err and says in err


def test_native_extract_refuses_differing_names_unless_mapped(world: World, tmp_path: Path,
                                                              capsys: pytest.CaptureFixture) -> None:
    cache = tmp_path / "cache"
    args = ["extract", "--encoder", "smolvla-native", "--policy", str(world.policy), "--dataset",
            str(world.dataset.root), "--grids", "4x4", "--num-workers", "0", "--cache", str(cache), "--no-progress"]
    assert main(args) == 2
    err = _one_error_line(capsys)
    assert all(side in err for side in BOTH_SIDES) and str(world.dataset.root) in err
    assert list_caches(cache) == []  # refused before anything was written
    assert main([*args, "--camera-map", MAP]) == 0
    assert capsys.readouterr().out.strip().splitlines()[-1].startswith("smolvla-native-")
    # a map means nothing to an encoder that serves any policy: refused, not ignored
    assert main(["extract", "--encoder", ENCODER, "--random-init", "--dataset", str(world.dataset.root),
                 "--camera-map", MAP, "--num-workers", "0", "--cache", str(cache), "--no-progress"]) == 2
    assert f"encoder '{ENCODER}' takes no --camera-map" in _one_error_line(capsys)
    # fit reads both caches through the one map; the native control's row records it too
    (encoder_cache,) = [c for c in list_caches(world.cache) if c.manifest.dataset.root == str(world.dataset.root)]
    shutil.copytree(world.cache / encoder_cache.key, cache / encoder_cache.key)
    out = tmp_path / "r.parquet"
    assert fit(world, out, "--controls", "native", cache=cache) == 2
    err = _one_error_line(capsys)
    assert all(side in err for side in BOTH_SIDES)
    assert fit(world, out, "--controls", "native", "--camera-map", MAP, cache=cache) == 0
    rows = results.read(out)
    assert sorted(rows["control"]) == ["native", "none"] and rows["camera_map"].to_list() == [MAP, MAP]


def test_train_tiny_takes_the_datasets_cameras_and_fits_match_them_by_name(world: World, tmp_path: Path,
                                                                          capsys: pytest.CaptureFixture) -> None:
    ds = str(world.dataset.root)
    train = ["train-tiny", "--backbone", "smolvla", "--dataset", ds, "--steps", "2"]
    assert main([*train, "--cameras", "eye_in_hand,agentview", "--out", str(tmp_path / "chosen")]) == 0
    assert main([*train, "--cache", str(tmp_path / "c")]) == 0  # default: all of the dataset's cameras
    default = Path(capsys.readouterr().out.strip().splitlines()[-1])
    smolvla = get_backbone("smolvla")
    assert smolvla.read_cameras(tmp_path / "chosen") == ("eye_in_hand", "agentview")
    assert smolvla.read_cameras(default) == ("agentview", "eye_in_hand")
    # naming the default cameras in the default order is the same policy: found again, not retrained
    assert main([*train, "--cache", str(tmp_path / "c"), "--cameras", "agentview,eye_in_hand"]) == 0
    assert f"reusing tiny smolvla trained by train-tiny: {default}" in capsys.readouterr().out
    out = tmp_path / "r.parquet"
    assert fit(world, out, policy=tmp_path / "chosen") == 0  # no map needed
    assert results.read(out)["camera_map"].to_list() == ["eye_in_hand=eye_in_hand,agentview=agentview"]
    assert main([*train, "--cameras", "wrist_image", "--out", str(tmp_path / "x")]) == 2
    err = _one_error_line(capsys)
    assert "'wrist_image' not in dataset" in err and "agentview, eye_in_hand" in err and ds in err
    with pytest.raises(SystemExit) as stopped:  # the field's rule, checked as the flag is parsed
        main([*train, "--cameras", "agentview,agentview", "--out", str(tmp_path / "x")])
    assert stopped.value.code == 2 and not (tmp_path / "x").exists()
    assert capsys.readouterr().err.strip().splitlines()[-1] == ("graftcache train-tiny: error: argument --cameras: "
                                                                "('agentview', 'agentview') must name at least one, "
                                                                "each once")


def test_train_tiny_refuses_a_folder_holding_another_checkpoint(world: World, tmp_path: Path,
                                                                capsys: pytest.CaptureFixture) -> None:
    folder = tmp_path / "smolvla"
    train = ["train-tiny", "--dataset", str(world.dataset.root), "--out", str(folder)]
    assert main([*train, "--backbone", "smolvla", "--steps", "2"]) == 0
    capsys.readouterr()
    before = {p.name: p.read_bytes() for p in folder.iterdir()}
    for extra in ([], ["--force"]):
        assert main([*train, "--backbone", "pi05", "--steps", "2", *extra]) == 2
        err = _one_error_line(capsys)
        assert str(folder) in err and "smolvla" in err and "pi05" in err
    # one without a training record (saved by hand) is named by its config
    assert main([*train[:-1], str(world.policy), "--backbone", "pi05", "--steps", "2"]) == 2
    assert str(world.policy) in (err := _one_error_line(capsys)) and "smolvla" in err and "pi05" in err
    # the same backbone trained otherwise is not silently taken for the one asked for
    assert main([*train, "--backbone", "smolvla", "--steps", "3"]) == 2
    assert "--force" in _one_error_line(capsys)
    assert {p.name: p.read_bytes() for p in folder.iterdir()} == before


def _recipe(world: World, tmp_path: Path, camera_map: str | None) -> Path:
    top = f'cache = "{world.cache}"\n' + (f'camera_map = "{camera_map}"\n' if camera_map else "")
    path = tmp_path / "recipe.toml"
    path.write_text(top + f"""
name = "t"
dataset = "{world.dataset.root}"
results = "{tmp_path / 'r.parquet'}"
suites = ["libero_spatial"]
seeds = [0]
controls = ["native"]
[[backbones]]
name = "smolvla"
policy = "{world.policy}"
[[encoders]]
name = "{ENCODER}"
random_init = true
[extract]
batch_size = 8
num_workers = 0
[fit]
steps = 2
batch_size = 4
eval_fraction = 0.5
eval_frames = 4
num_denoise_steps = 2
num_workers = 0
""")
    return path


def test_sweep_refuses_before_extracting_and_passes_its_map_to_fits_and_native_extracts(world: World,
                                                                                       tmp_path: Path) -> None:
    keys = {c.key for c in list_caches(world.cache)}
    with pytest.raises(GraftcacheError, match="camera names differ") as e:
        run_sweep(load_recipe(_recipe(world, tmp_path, None)), log=lambda _: None)
    assert all(side in str(e.value) for side in BOTH_SIDES)
    assert {c.key for c in list_caches(world.cache)} == keys and not (tmp_path / "r.parquet").exists()
    state = run_sweep(load_recipe(_recipe(world, tmp_path, MAP)), log=lambda _: None)
    rows = results.read(tmp_path / "r.parquet")
    assert sorted(rows["control"]) == ["native", "none"] and rows["camera_map"].to_list() == [MAP, MAP]
    assert f"--camera-map {MAP}" in state.commands[state.native_caches["smolvla"]]


def test_recipe_camera_map_is_checked_as_it_is_read(world: World, tmp_path: Path) -> None:
    with pytest.raises(RecipeError, match=r"recipe.toml: camera_map: .*'agentview' would feed policy cameras"):
        load_recipe(_recipe(world, tmp_path, "image=agentview,image2=agentview"))
    path = _recipe(world, tmp_path, None)
    path.write_text(path.read_text() + f'camera_map = "{MAP}"\n')  # in [fit]: the recipe product sets it, not a table
    with pytest.raises(RecipeError, match=r"\[fit\]: unknown key\(s\) camera_map"):
        load_recipe(path)
