"""Stage 1 end to end: `extract()` against an independent computation, cache keys and reuse, the
copied index / low-dim columns, resume after SIGKILL (byte-identical), bad inputs, ls/info/verify."""

from __future__ import annotations

import json
import signal
import sys
from functools import partial
from pathlib import Path

import numpy as np
import pytest
import timm
import torch
import torch.nn.functional as F
from fixtures.resolutions import RESOLUTIONS
from helpers.datasets import LENGTHS, TASKS, Written, build_lerobot
from helpers.probes import hang_after_blocks, kill_after_blocks, start_process
from helpers.requests import extract_request
from PIL import Image

from graftcache.cli import main
from graftcache.encoders.fingerprint import TOLERANCE
from graftcache.extract import ExtractRequest, extract
from graftcache.runtime import CPU_BF16_ENV
from graftcache.store import FeatureCache, list_caches

ENCODER = "timm:vit_tiny_patch16_224"  # a real ViT architecture, cheap on CPU
GRAFTCACHE = Path(sys.executable).with_name("graftcache")


_req = partial(extract_request, encoder=ENCODER, grids=("unpooled", "2x2", "7x7"), seed=0, batch_size=8, block_frames=6)


def _quiet(_: str) -> None:
    pass


@pytest.fixture(scope="module")
def extracted(v3_image: Written, tmp_path_factory: pytest.TempPathFactory):
    root = tmp_path_factory.mktemp("cache")
    return _req(v3_image.root, root), extract(_req(v3_image.root, root), log=_quiet)


@pytest.fixture(scope="module")
def unpooled_only(extracted, v3_image: Written) -> FeatureCache:
    """The default extraction (the encoder's own grid alone) beside `extracted`, in the same blocks and batches."""
    req, _ = extracted
    assert ExtractRequest.grids == ("unpooled",)
    return FeatureCache(extract(_req(v3_image.root, Path(req.cache), grids=ExtractRequest.grids), log=_quiet).path)


def _reference_features(frames: np.ndarray, model: torch.nn.Module, grid: tuple[int, int]) -> np.ndarray:
    """Written here, independently of graftcache: PIL float resize, timm's mean/std, forward_features,
    drop the prefix token, adaptive average pool."""
    cfg = timm.data.resolve_data_config({}, model=model)
    size = cfg["input_size"][-1]
    mean, std = np.array(cfg["mean"]), np.array(cfg["std"])
    pixels = []
    for frame in frames:
        chans = [np.asarray(Image.fromarray(frame[..., c].astype(np.float32), mode="F")
                            .resize((size, size), Image.BICUBIC)) for c in range(3)]
        x = (np.clip(np.stack(chans, -1), 0, 255) / 255 - mean) / std
        pixels.append(torch.from_numpy(x.transpose(2, 0, 1)).float())
    with torch.no_grad():
        tokens = model.forward_features(torch.stack(pixels))[:, model.num_prefix_tokens:]
    side = int(tokens.shape[1] ** 0.5)
    fmap = tokens.reshape(len(frames), side, side, -1).permute(0, 3, 1, 2)
    return F.adaptive_avg_pool2d(fmap, grid).flatten(2).transpose(1, 2).numpy()


@pytest.fixture(scope="module", params=sorted(RESOLUTIONS), ids=[f"auto={r}" for r in sorted(RESOLUTIONS)])
def extracted_auto(request: pytest.FixtureRequest, v3_image: Written, tmp_path_factory: pytest.TempPathFactory):
    """The same extraction under both resolutions of `--compute-dtype auto` (fixtures/resolutions.py; module-scoped
    here, so the extraction runs once per resolution)."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv(CPU_BF16_ENV, RESOLUTIONS[request.param])
        req = _req(v3_image.root, tmp_path_factory.mktemp("cache"))
        return request.param, extract(req, log=_quiet)


def test_features_equal_an_independent_computation(extracted_auto, v3_image: Written) -> None:
    """Within the tolerance of the compute dtype the cache was made in (the one `auto` resolved to): fp32 to
    fp16 storage precision, bf16 within the numerics check's bound (5% of the output's RMS): bf16 keeps 8
    mantissa bits, and a 12-block ViT compounds their rounding to ~2% of an element's scale."""
    dtype, result = extracted_auto
    cache = FeatureCache(result.path)
    assert cache.complete and result.n_frames == sum(LENGTHS) and not result.reused
    assert cache.manifest.compute_dtype == dtype  # what `auto` resolved to, recorded
    # the same random-init weights, put into a model built here
    from graftcache.encoders import load_encoder

    model = timm.create_model("vit_tiny_patch16_224", pretrained=False, num_classes=0)
    model.load_state_dict(load_encoder(ENCODER, random_init=True, seed=0).model.state_dict())
    model.eval()
    for key in v3_image.cameras:
        frames = np.concatenate([v3_image.frames[ep, key] for ep in range(len(LENGTHS))])
        cam = key.rsplit(".", 1)[-1]
        for grid in ((14, 14), (2, 2), (7, 7)):  # 14x14: the ViT's own patch grid (`unpooled`), stored as it is
            want = _reference_features(frames, model, grid)
            got = cache.read_features(cam, f"{grid[0]}x{grid[1]}").float().numpy()
            assert got.dtype == np.float32 and got.shape == want.shape == (len(frames), grid[0] * grid[1], 192)
            if dtype == "fp32":
                np.testing.assert_allclose(got, want, rtol=1e-2, atol=1e-2)
            else:
                drift = np.abs(got - want).max() / np.sqrt(np.mean(want**2))
                assert drift <= TOLERANCE[dtype], (cam, grid, drift)


def test_index_lowdim_and_manifest_are_copied_in(extracted, v3_image: Written) -> None:
    _, result = extracted
    cache = FeatureCache(result.path)
    index = cache.index()
    assert index["episode_index"].to_list() == [ep for ep, n in enumerate(LENGTHS) for _ in range(n)]
    assert index["frame_index"].to_list() == [t for n in LENGTHS for t in range(n)]
    state = np.stack(index["state"].to_numpy())
    np.testing.assert_array_equal(state, np.concatenate([v3_image.state[ep] for ep in range(len(LENGTHS))]))
    action = np.stack(index["action"].to_numpy())
    np.testing.assert_array_equal(action, np.concatenate([v3_image.action[ep] for ep in range(len(LENGTHS))]))
    m = cache.manifest
    assert [m.tasks[i] for i in index["task_index"].to_list()] == [TASKS[ep] for ep, n in enumerate(LENGTHS)
                                                                       for _ in range(n)]
    assert m.suites[index["suite_index"][0]] == "libero_spatial"
    assert m.random_init is True and m.weights["seed"] == 0 and len(m.weights_sha256) == 64
    assert m.dataset.codebase_version == "v3.0" and m.storage_dtype == "fp16"
    assert m.encoder["preprocessing"]["mean"] == [0.5, 0.5, 0.5]
    assert set(m.versions) >= {"torch", "timm", "transformers", "lerobot", "zarr"}
    json.dumps(m.to_dict())


def test_cache_key_follows_the_numbers_only(extracted, v3_image: Written) -> None:
    req, result = extracted
    same = extract(_req(v3_image.root, Path(req.cache), batch_size=3, num_workers=1), log=_quiet)
    assert same.key == result.key and same.reused and same.frames_encoded == 0
    keys = {result.key}
    for change in ({"grids": ("2x2",)}, {"seed": 1}, {"storage_dtype": "fp32"}, {"episodes": (0, 2)},
                   {"cameras": ("image",)}):
        r = extract(_req(v3_image.root, Path(req.cache), **change), log=_quiet)
        assert r.key not in keys, change
        keys.add(r.key)
        if "grids" in change:  # pooled grids only: no stored grid is the encoder's own
            assert FeatureCache(r.path).manifest.unpooled_grid is None


def test_unpooled_grid_is_stored_once_under_one_key_whatever_its_spelling(
        extracted, unpooled_only: FeatureCache, v3_image: Written, capsys: pytest.CaptureFixture) -> None:
    """`unpooled` (the default) stores the encoder's own grid (ViT-Ti/16 at 224 px: 14x14) unpooled and nothing
    else; spelled out as 14x14, or both, it is the same cache; the manifest names the unpooled grid."""
    req, with_pooled = extracted
    m = unpooled_only.manifest
    assert m.grids == ["14x14"] and m.unpooled_grid == "14x14" and m.encoder["grid"] == [14, 14]
    assert {p: s for p, s in unpooled_only.layout["arrays"].items() if p.startswith("features/")} == \
        {"features/image/14x14": [196, 192], "features/image2/14x14": [196, 192]}
    pooled = FeatureCache(with_pooled.path)
    assert pooled.manifest.grids == ["14x14", "2x2", "7x7"] and pooled.manifest.unpooled_grid == "14x14"
    for cam in ("image", "image2"):  # the same activations, stored as they are
        assert torch.equal(unpooled_only.read_features(cam, "14x14"), pooled.read_features(cam, "14x14"))
    for spelled in (("14x14",), ("14x14", "unpooled")):
        again = extract(_req(v3_image.root, Path(req.cache), grids=spelled), log=_quiet)
        assert again.key == unpooled_only.key and again.reused, spelled
    assert main(["extract", "--encoder", ENCODER, "--random-init", "--dataset", str(v3_image.root), "--num-workers",
                 "0", "--batch-size", "8", "--block-frames", "6", "--no-progress", "--cache", req.cache]) == 0
    assert capsys.readouterr().out.strip().splitlines()[-1] == unpooled_only.key  # the CLI's default is unpooled too


@pytest.mark.parametrize("grid", [(7, 7), (2, 2), (4, 4), (3, 5)])
def test_read_grid_pools_the_stored_unpooled_grid(extracted, unpooled_only: FeatureCache, grid: tuple[int, int],
                                                monkeypatch: pytest.MonkeyPatch) -> None:
    """read_grid from an unpooled-only cache equals adaptive average pooling of the stored 14x14 grid written here
    (in fp32, rounded to fp16), read a block at a time in any row order. Against the grids pooled at extraction
    (fp32 activations pooled, rounded once) it differs by at most 3 x 2^-11 of the largest magnitude pooled
    (half an fp16 step on each input and on the mean; the frame's per-channel maximum bounds the window's)."""
    from graftcache.fit import data

    monkeypatch.setattr(data, "POOL_READ_BYTES", 1)  # one 6-frame block per read: 3 reads
    rows = np.array([17, 0, 5, 6, 11, 12])
    pooled = FeatureCache(extracted[1].path)
    for cam in ("image", "image2"):
        got = data.read_grid(unpooled_only, cam, grid, rows)
        stored = unpooled_only.read_features(cam, "14x14")[rows].float().reshape(len(rows), 14, 14, 192)
        want = F.adaptive_avg_pool2d(stored.permute(0, 3, 1, 2), grid).flatten(2).transpose(1, 2).half()
        assert got.dtype == torch.float16 and got.shape == (len(rows), grid[0] * grid[1], 192)
        assert torch.equal(got, want)
        name = f"{grid[0]}x{grid[1]}"
        if name in pooled.manifest.grids:
            at_extract = pooled.read_features(cam, name, rows)
            assert torch.equal(data.read_grid(pooled, cam, grid, rows), at_extract)  # a stored grid is read as is
            bound = 3 * 2**-11 * stored.abs().amax(dim=(1, 2)).unsqueeze(1) + 2**-24
            assert ((got.float() - at_extract.float()).abs() <= bound).all()


@pytest.fixture(scope="module")
def long_dataset(tmp_path_factory: pytest.TempPathFactory) -> Written:
    """Three 24-frame episodes, 18 blocks of 4: enough to interrupt extraction after 3 and before the last."""
    return build_lerobot(tmp_path_factory, "long", video=True, lengths=(24, 24, 24))


def _extract_args(dataset: Path, cache: Path, workers: int) -> list[str]:
    return ["extract", "--encoder", "resnet18", "--random-init", "--dataset", str(dataset), "--grids", "2x2",
            "--block-frames", "4", "--batch-size", "4", "--num-workers", str(workers), "--cache", str(cache),
            "--no-progress"]


@pytest.mark.slow
def test_sigkill_then_rerun_is_byte_identical_to_an_uninterrupted_run(long_dataset: Written, tmp_path: Path,
                                                                      capsys: pytest.CaptureFixture) -> None:
    """The process (and its decode worker) is killed after 3 of 18 blocks; the rerun, in this process and with
    in-process decoding, resumes and ends byte-identical to an uninterrupted run."""
    killed_root, clean_root = tmp_path / "killed", tmp_path / "clean"
    proc = start_process(_extract_args(long_dataset.root, killed_root, workers=1), prelude=hang_after_blocks(3))
    assert kill_after_blocks(proc, killed_root, 3).code == -signal.SIGKILL
    (cache,) = list_caches(killed_root)
    assert not cache.complete and len(cache.blocks_done()) == 3 < cache.layout["n_blocks"]
    assert main(["verify", cache.key, "--cache", str(killed_root)]) == 1  # incomplete is a failing verdict

    capsys.readouterr()
    assert main(_extract_args(long_dataset.root, killed_root, workers=0)) == 0
    assert "resuming" in capsys.readouterr().out
    assert main(_extract_args(long_dataset.root, clean_root, workers=0)) == 0
    a, b = FeatureCache(killed_root / cache.key), FeatureCache(clean_root / cache.key)
    assert a.complete and b.complete
    for cam in ("image", "image2"):
        assert a.group[f"features/{cam}/2x2"][...].tobytes() == b.group[f"features/{cam}/2x2"][...].tobytes()
    assert main(["verify", cache.key, "--cache", str(killed_root)]) == 0


def test_ls_info_verify(extracted, capsys: pytest.CaptureFixture) -> None:
    req, result = extracted
    assert main(["ls", "--cache", req.cache]) == 0
    out = capsys.readouterr().out
    assert result.key[:12] in out and "complete" in out and "random-init" in out
    assert main(["info", result.key, "--cache", req.cache]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["complete"] is True and info["encoder"]["name"] == ENCODER
    assert main(["verify", result.key, "--cache", req.cache]) == 0
    assert "all checksums match" in capsys.readouterr().out
    assert main(["verify", "no-such-key", "--cache", req.cache]) == 2
    assert "no-such-key" in capsys.readouterr().err


def test_verify_names_a_corrupted_block(v3_image: Written, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    result = extract(_req(v3_image.root, tmp_path, grids=("2x2",), block_frames=6), log=_quiet)
    cache = FeatureCache(result.path)
    arr = cache.group["features/image/2x2"]
    arr[7] = arr[7] + 1  # flip values inside block 1
    assert main(["verify", result.key, "--cache", str(tmp_path)]) == 1
    assert "features/image/2x2 frames 6-11 checksum mismatch" in capsys.readouterr().out


def _bad(tmp_path: Path, dataset: Path, capsys: pytest.CaptureFixture, *extra: str) -> str:
    cache = tmp_path / "cache"
    code = main(["extract", "--encoder", ENCODER, "--random-init", "--dataset", str(dataset), "--grids", "2x2",
                 "--num-workers", "0", "--no-progress", "--cache", str(cache), *extra])
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1, err
    assert not cache.exists() or not [c for c in list_caches(cache) if c.complete]
    return err


def test_bad_inputs_give_one_line_errors_and_nothing_complete(v3_video: Written, tmp_path: Path,
                                                                capsys: pytest.CaptureFixture) -> None:
    import shutil

    assert f"{tmp_path / 'absent'}: no such dataset folder" in _bad(tmp_path, tmp_path / "absent", capsys)
    broken = tmp_path / "broken"
    shutil.copytree(v3_video.root, broken)
    info = json.loads((broken / "meta" / "info.json").read_text())
    (broken / "meta" / "info.json").write_text(json.dumps({**info, "codebase_version": "v9.9"}))
    assert "v9.9" in _bad(tmp_path, broken, capsys)
    (broken / "meta" / "info.json").write_text(json.dumps(info))
    assert "'wrist'" in _bad(tmp_path, broken, capsys, "--cameras", "wrist")
    (broken / "meta" / "info.json").unlink()
    assert f"{broken / 'meta' / 'info.json'}: missing" in _bad(tmp_path, broken, capsys)

    short = tmp_path / "short"
    shutil.copytree(v3_video.root, short)
    (video,) = (short / "videos" / "observation.images.image2").rglob("*.mp4")
    video.write_bytes(video.read_bytes()[: video.stat().st_size // 3])
    err = _bad(tmp_path, short, capsys)
    assert video.name in err and "episode" in err
