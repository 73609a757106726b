"""Loading policies: the failures (a hub id missing from the HF cache, a foreign or wrong-type folder, a tiny
marker). Loading back by folder and hub id, a missing weight and missing processors, for every backbone: the
contract (tests/backbones/test_contract.py)."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest
from helpers.backbones import tiny

from graftcache.backbones import get_backbone, load_backbone
from graftcache.backbones.base import vlm_folder
from graftcache.backbones.tiny import TINY_MARKER
from graftcache.errors import BackboneError
from graftcache.graft import GraftProjector

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # tests/fixtures/torch_threads.py


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


def test_a_vlm_folder_is_the_shipped_one_for_tiny_policies_else_local_else_cached(tmp_path: Path) -> None:
    """The precedence every adapter's VLM files follow: a tiny policy's shipped folder even where its saved config
    names a folder that exists (the path of the install that saved it), a local folder as named, else the HF cache,
    whose miss is one line naming what was looked for."""
    shipped, local = tmp_path / "shipped", tmp_path / "local"
    local.mkdir()
    assert vlm_folder(str(local), {"backbone": "eo1"}, shipped, "EO-1's processor") == shipped
    assert vlm_folder(str(local), None, shipped, "EO-1's processor") == local
    with pytest.raises(BackboneError, match=r"^EO-1's processor 'org/absent' is neither a local folder nor in the "):
        vlm_folder("org/absent", None, shipped, "EO-1's processor")
