"""Loading policies through lerobot's from_pretrained: local folders, the HF cache, and the failures."""

from __future__ import annotations

import json
import os
import re
import shutil
from pathlib import Path

import pytest
import torch
from helpers.backbones import fixed_noise_time, lowdim_stats, raw_features, raw_images, tiny
from safetensors.torch import load_file, save_file

from graftcache.backbones import get_backbone, load_backbone
from graftcache.backbones.tiny import TINY_MARKER
from graftcache.errors import BackboneError
from graftcache.graft import GraftProjector

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # tests/fixtures/torch_threads.py

NAMES = ("smolvla", "pi05", "pi0", "pi0_fast")


def _as_hub_cache_entry(folder: Path, repo_id: str) -> Path:
    """Lay `folder` out as the HF cache does: models--org--name/{refs/main, snapshots/<rev>/...}."""
    root = Path(os.environ["HF_HUB_CACHE"]) / f"models--{repo_id.replace('/', '--')}"
    revision = "0123456789abcdef0123456789abcdef01234567"
    shutil.copytree(folder, root / "snapshots" / revision)
    (root / "refs").mkdir(parents=True)
    (root / "refs" / "main").write_text(revision)
    return root / "snapshots" / revision


def _grafted_predictions(adapter, seed: int = 0) -> torch.Tensor:
    torch.manual_seed(seed)
    adapter.graft(GraftProjector(32, adapter.lm_width))
    batch = adapter.prepare(raw_features(adapter, 3, enc_dim=32))
    noise, _ = fixed_noise_time(adapter, 3)
    return adapter.predict(batch, noise)


@pytest.mark.parametrize("name", NAMES)
def test_saved_checkpoint_loads_back_from_a_folder_and_the_hub_cache(name: str, tmp_path: Path) -> None:
    original = tiny(name, seed=2)
    folder = original.save(tmp_path / "ckpt")
    files = {p.name for p in folder.iterdir()}
    assert {"config.json", "model.safetensors", "policy_preprocessor.json", "policy_postprocessor.json",
            TINY_MARKER} <= files

    loaded = load_backbone(name, folder)
    assert loaded.random_init and loaded.source == str(folder)  # a tiny checkpoint is never released weights
    assert loaded.policy_sha256 == original.policy_sha256
    reference = original.policy.state_dict()
    assert all(torch.equal(reference[k], v) for k, v in loaded.policy.state_dict().items())
    # the normalisation stats travelled with the processors
    raw = raw_features(loaded, 3, enc_dim=32)
    torch.testing.assert_close(original.preprocessor(dict(raw))["observation.state"],
                               loaded.preprocessor(dict(raw))["observation.state"])

    repo_id = f"graftcache-tests/tiny-{name}"
    _as_hub_cache_entry(folder, repo_id)
    from_cache = load_backbone(name, repo_id)
    assert from_cache.policy_sha256 == original.policy_sha256
    torch.testing.assert_close(_grafted_predictions(from_cache), _grafted_predictions(original))


def test_missing_hub_id_names_what_was_looked_for() -> None:
    with pytest.raises(BackboneError) as err:
        load_backbone("smolvla", "lerobot/smolvla_base")
    message = str(err.value)
    assert "'lerobot/smolvla_base'" in message and "models--lerobot--smolvla_base" in message
    assert os.environ["HF_HUB_CACHE"] in message
    with pytest.raises(BackboneError, match="no such folder"):
        load_backbone("pi05", "./no/such/checkpoint")


def test_wrong_policy_type_and_foreign_folders_are_refused(tmp_path: Path) -> None:
    folder = tiny("smolvla").save(tmp_path / "smol")
    with pytest.raises(BackboneError, match="tiny smolvla checkpoint, not pi05"):
        load_backbone("pi05", folder)
    (folder / TINY_MARKER).unlink()
    with pytest.raises(BackboneError, match="a 'smolvla' policy, not 'pi05'"):
        load_backbone("pi05", folder)
    (tmp_path / "empty").mkdir()
    with pytest.raises(BackboneError, match="no config.json"):
        load_backbone("smolvla", tmp_path / "empty")


@pytest.mark.parametrize(("name", "key"), [(n, "model.action_out_proj.weight") for n in NAMES[:3]] + [
    ("pi0_fast", "model.paligemma_with_expert.paligemma.model.multi_modal_projector.linear.weight")])  # no action head
def test_checkpoint_missing_weights_is_an_error_not_a_random_model(name: str, key: str, tmp_path: Path) -> None:
    folder = tiny(name).save(tmp_path / "ckpt")
    weights = load_file(folder / "model.safetensors")
    del weights[key]
    save_file(weights, folder / "model.safetensors")
    with pytest.raises(BackboneError, match=rf"\(1 missing, 0 mis-shaped, 0 unexpected\): missing {re.escape(key)}"):
        load_backbone(name, folder)


@pytest.mark.parametrize("name", NAMES)
def test_checkpoint_without_processors_needs_stats(name: str, tmp_path: Path) -> None:
    folder = tiny(name).save(tmp_path / "ckpt")
    for path in folder.glob("policy_*processor*"):
        path.unlink()
    with pytest.raises(BackboneError, match="no policy_preprocessor.json; pass dataset_stats"):
        load_backbone(name, folder)
    loaded = load_backbone(name, folder, dataset_stats=lowdim_stats())
    batch = loaded.prepare(raw_images(loaded, 2))
    torch.testing.assert_close(batch["action"][0, 0], raw_images(loaded, 2)["action"][0, 0] / 1.2 if name == "pi05"
                               else (raw_images(loaded, 2)["action"][0, 0] - 0.1) / 0.8)  # QUANTILES | MEAN_STD


def test_tiny_needs_stats_and_grafted_policies_cannot_be_saved(tmp_path: Path) -> None:
    with pytest.raises(BackboneError, match="pass dataset_stats"):
        get_backbone("smolvla").load("tiny")
    adapter = tiny("pi05")
    adapter.graft(GraftProjector(8, adapter.lm_width))
    with pytest.raises(BackboneError, match="save before graft"):
        adapter.save(tmp_path / "x")


def test_tiny_marker_records_the_pi05_geometry(tmp_path: Path) -> None:
    folder = tiny("pi05").save(tmp_path / "ckpt")
    marker = json.loads((folder / TINY_MARKER).read_text())
    assert marker["backbone"] == "pi05"
    assert marker["geometry"]["lm_width"] == 128 and marker["geometry"]["image_size"] == 56
    (folder / TINY_MARKER).write_text("{not json")
    with pytest.raises(BackboneError, match="unreadable tiny-backbone marker"):
        load_backbone("pi05", folder)
