"""The dose family `noise-A` (graftcache/fit/dose.py): its names, its levels ordered by the correlation they keep
(sqrt(1 - A), numpy's), one draw per (seed, frame key) whichever batch or path the frame comes through (a fit's
batches, the exported policy's observation), and a tiny fit that records the control and saves the spread."""

from __future__ import annotations

import json
import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from helpers.datasets import Written
from helpers.world import World
from safetensors.torch import load_file

from graftcache import results
from graftcache.errors import ExportError, FitError
from graftcache.export.bundle import export_run
from graftcache.export.features import CellFeatures
from graftcache.fit.controls import get_control
from graftcache.fit.data import LowDim, load_lowdim, read_grid
from graftcache.fit.dose import SPREAD_FILE, Dose, Seen, dosed
from graftcache.fit.local import Fitter
from graftcache.fit.loop import learner
from graftcache.graft import feature_key
from graftcache.pooling import parse_grid

ENCODER = "timm:vit_tiny_patch16_224"


def _features(n: int, seed: int = 0) -> dict[str, torch.Tensor]:
    """Two cameras of [n, 4, 6] features, each channel with its own mean and scale."""
    g = torch.Generator().manual_seed(seed)
    scale, mean = torch.linspace(0.1, 3.0, 6), torch.linspace(-2.0, 2.0, 6)
    return {c: torch.randn(n, 4, 6, generator=g) * scale + mean for c in ("agentview", "wrist")}


def _spread(features: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    return {c: torch.from_numpy(f.reshape(-1, f.shape[-1]).numpy().std(axis=0)).float() for c, f in features.items()}


@pytest.mark.parametrize("name", ["noise-1.5", "noise-x", "noise-0", "noise-1", "noise-nan", "noise-"])
def test_a_bad_dose_is_refused_in_one_line(name: str) -> None:
    with pytest.raises(FitError) as e:
        get_control(name)
    assert str(e.value) == (f"control {name!r}: expected noise-A with A strictly between 0 and 1, e.g. noise-0.5 (0 "
                            "is the plain cell, 1 the blind zero-image control)")


def test_a_dose_is_named_one_way_and_is_a_closed_loop_control() -> None:
    control = get_control("noise-0.50")
    assert (control.name, control.dose, control.closed_loop, control.train) == ("noise-0.5", 0.5, True, True)
    assert get_control("noise-1e-3").name == "noise-0.001"
    assert get_control("none").dose is None and get_control("zero-image").dose is None
    with pytest.raises(FitError, match=r", pool-HxW, noise-A$"):
        get_control("noise")


def test_levels_keep_sqrt_one_minus_a_of_the_features_at_their_scale() -> None:
    """Per channel, the dosed features correlate with the clean ones by sqrt(1 - A) and keep their variance, so the
    levels are ordered by a measured quantity."""
    clean = _features(4000)
    spread = _spread(clean)
    keys = np.arange(len(clean["agentview"]))
    measured = []
    for level in (0.1, 0.25, 0.5, 0.75, 0.9):
        out = dosed(clean, keys, level, spread, seed=3)
        x, y = clean["wrist"].reshape(-1, 6).numpy(), out["wrist"].reshape(-1, 6).numpy()
        corr = np.array([np.corrcoef(x[:, j], y[:, j])[0, 1] for j in range(6)])
        np.testing.assert_allclose(corr, math.sqrt(1 - level), atol=0.02)
        np.testing.assert_allclose(y.std(axis=0), x.std(axis=0), rtol=0.05)
        measured.append(corr.mean())
    assert measured == sorted(measured, reverse=True)


def test_a_frame_meets_one_draw_whatever_its_batch() -> None:
    clean = _features(2)
    spread = _spread(_features(50))
    both = dosed(clean, np.array([3, 7]), 0.5, spread, seed=1)  # frames keyed 3 and 7
    alone = dosed({c: f[1:2] for c, f in clean.items()}, np.array([7]), 0.5, spread, seed=1)
    for c in clean:
        torch.testing.assert_close(both[c][1:2], alone[c], rtol=0, atol=0)
    other_seed = dosed(clean, np.array([3, 7]), 0.5, spread, seed=2)
    other_key = dosed(clean, np.array([4, 7]), 0.5, spread, seed=1)
    assert not torch.equal(other_seed["agentview"][0], both["agentview"][0])
    assert not torch.equal(other_key["agentview"][0], both["agentview"][0])
    torch.testing.assert_close(other_key["agentview"][1], both["agentview"][1], rtol=0, atol=0)
    with pytest.raises(FitError, match=r"^3 keys for 2 frames of dose features$"):
        dosed(clean, np.array([3, 7, 8]), 0.5, spread, seed=1)


class _Buffer:
    """A shuffle buffer that hands out fixed frames (split positions `owners`)."""

    def __init__(self, owners: np.ndarray, features: dict[str, torch.Tensor]) -> None:
        self.owners, self.features = owners, features

    def draw(self, k: int, generator: torch.Generator) -> tuple[np.ndarray, dict[str, torch.Tensor]]:
        return self.owners, self.features


def _low(rows: np.ndarray) -> LowDim:
    n = len(rows)
    return LowDim(rows, rows, np.zeros(n, dtype=np.int64), np.arange(n), torch.zeros(n, 8),
                  torch.zeros(n, dtype=torch.long), np.arange(n), np.full(n, n), torch.zeros(n, 7), 2, ("task",),
                  np.zeros(n, dtype=bool))


def test_fit_and_export_feed_the_same_dosed_features_for_a_seed_and_frame_key() -> None:
    """A fit's batch (its frames' cache rows as keys) and the exported policy's observation (the chunks since its
    reset as the key) go through one draw: frame key 0 of seed 5 is the same features both ways, the export's second
    chunk is key 1, and a reset starts the episode again."""
    clean = _features(2)
    dose = Dose(0.5, _spread(_features(50)), seed=5)
    low = _low(np.array([1, 0]))  # split positions 0, 1 are cache rows 1, 0
    cams = {"camera1": "agentview", "camera2": "wrist"}
    fit = learner(low, _Buffer(np.array([1, 0]), clean), cams, [torch.nn.Parameter(torch.zeros(1))], batch_size=2,
                  lr=1e-3, seed=0, transform=Seen(get_control("noise-0.5").transform, dose))
    batch = fit.draw(torch.Generator())
    want = dosed(clean, np.array([0, 1]), 0.5, dose.spread, seed=5)  # owners 1, 0 -> cache rows 0, 1
    for policy_camera, camera in cams.items():
        torch.testing.assert_close(batch[feature_key(policy_camera)], want[camera], rtol=0, atol=0)

    class Fixed(CellFeatures):
        def __init__(self, frame: int) -> None:
            self.dose, self.chunks, self.encoder = dose, 0, SimpleNamespace(device="cpu")
            self.frame = frame

        def __call__(self, images: torch.Tensor) -> torch.Tensor:
            return clean[self.camera][self.frame:self.frame + 1]

        def observe(self, batch: dict, cameras: dict, where: str) -> dict:
            self.camera = "agentview"
            return super().observe(batch, cameras, where)

    export = Fixed(0)
    observation = {"observation.images.agentview": torch.zeros(1, 3, 8, 8)}
    first = export.observe(observation, {"camera1": "agentview"}, "export")[feature_key("camera1")]
    torch.testing.assert_close(first, want["agentview"][:1], rtol=0, atol=0)
    second = export.observe(observation, {"camera1": "agentview"}, "export")[feature_key("camera1")]
    key1 = dosed({"agentview": clean["agentview"][:1]}, np.array([1]), 0.5, dose.spread, seed=5)["agentview"]
    torch.testing.assert_close(second, key1, rtol=0, atol=0)
    export.reset()
    again = export.observe(observation, {"camera1": "agentview"}, "export")[feature_key("camera1")]
    torch.testing.assert_close(again, first, rtol=0, atol=0)


@pytest.fixture(scope="module")
def world(v3_video: Written, tmp_path_factory: pytest.TempPathFactory) -> World:
    return World(tmp_path_factory.mktemp("dose"), v3_video, encoder=ENCODER, extract_settings={"batch_size": 8},
                 fit={"steps": 3, "eval_frames": 4, "num_denoise_steps": 2})


def test_a_tiny_fit_records_its_dose_saves_its_spread_and_reproduces(world: World, tmp_path: Path) -> None:
    fitter = Fitter(world.request(controls=("noise-0.5",), results=str(tmp_path / "a.parquet")), log=lambda _: None)
    fitter.run()
    by = {r["control"]: r for r in results.read(tmp_path / "a.parquet").iter_rows(named=True)}
    assert set(by) == {"none", "noise-0.5"}
    row = by["noise-0.5"]
    assert row["eval_mse"] != by["none"]["eval_mse"] and row["cache_key"] == by["none"]["cache_key"]
    folder = next(fitter.plan.run_folder(c) for c in fitter.plan.cells() if c.run_id == row["run_id"])
    split = json.loads((folder / "projector.json").read_text())["split"]
    cache = world.encoder_cache
    low = load_lowdim(cache, "libero_spatial", chunk=2).subset(split["train_episodes"])
    for camera, spread in load_file(str(folder / SPREAD_FILE)).items():  # numpy's std over frames and tokens
        frames = read_grid(cache, camera, parse_grid(row["pool_grid"]), np.sort(low.rows)).double().numpy()
        np.testing.assert_allclose(spread.numpy(), frames.reshape(-1, frames.shape[-1]).std(axis=0), rtol=1e-5,
                                   atol=1e-6)
    again = Fitter(world.request(controls=("noise-0.5",), results=str(tmp_path / "b.parquet"),
                                 under=tmp_path / "b"), log=lambda _: None)
    again.run()
    rerun = {r["control"]: r for r in results.read(tmp_path / "b.parquet").iter_rows(named=True)}["noise-0.5"]
    assert (rerun["run_id"], rerun["eval_mse"]) == (row["run_id"], row["eval_mse"])
    (folder / SPREAD_FILE).unlink()  # an export needs it: refused in one line, before anything loads
    with pytest.raises(ExportError, match=rf"^run {row['run_id']}: {folder / SPREAD_FILE} is missing \(the feature "
                       r"spread its dose noise was scaled by\); fit the cell again to export it$"):
        export_run(row["run_id"], tmp_path / "a.parquet", tmp_path / "export", cache=str(world.cache),
                   runs=str(folder.parent))
