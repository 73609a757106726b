"""The backbone registry is the folders of graftcache/backbones/: every registered backbone has every required piece
(graftcache.backbone_table.PIECES: its adapter class, its tiny configuration), found by convention."""

from __future__ import annotations

import inspect
import types
from importlib import import_module
from pathlib import Path

import pytest

from graftcache.backbone_table import BACKBONES, FOLDER, PIECES, backbone_module, missing_pieces
from graftcache.backbones import get_backbone
from graftcache.backbones.activation_checkpointing import ActivationCheckpointing
from graftcache.backbones.attention import Attention
from graftcache.backbones.base import BackboneAdapter
from graftcache.backbones.objectives import FlowObjective, Objective, TokenObjective
from graftcache.backbones.spec import BackboneSpec
from graftcache.errors import BackboneError


def test_the_registry_lists_the_folders_holding_an_adapter() -> None:
    folders = {p.name for p in FOLDER.iterdir() if p.is_dir() and (p / "adapter.py").is_file()}
    assert set(BACKBONES) == folders
    assert all(BACKBONES[name] == backbone_module(name) for name in BACKBONES)


def test_a_folder_lacking_a_piece_is_named(tmp_path: Path) -> None:
    (tmp_path / "adapter.py").write_text("")
    assert missing_pieces(tmp_path) == [p for p in PIECES if p != "adapter"]


@pytest.mark.parametrize("name", sorted(BACKBONES))
def test_every_registered_backbone_has_every_piece(name: str) -> None:
    assert missing_pieces(FOLDER / name) == [], f"graftcache/backbones/{name}/ lacks a required piece"
    adapter = get_backbone(name)
    assert issubclass(adapter, BackboneAdapter) and not inspect.isabstract(adapter), adapter.__abstractmethods__
    assert adapter.name == name and adapter.__module__ == backbone_module(name)
    assert callable(import_module(backbone_module(name, "tiny")).build_tiny)


@pytest.mark.parametrize("name", sorted(BACKBONES))
def test_every_registered_backbone_declares_a_spec_its_hooks_agree_with(name: str) -> None:
    adapter = get_backbone(name)
    spec = adapter.spec
    assert isinstance(spec, BackboneSpec)
    assert spec.activation_checkpointing == (
        adapter._switch_activation_checkpointing is not ActivationCheckpointing._switch_activation_checkpointing)
    assert (len(spec.attentions) > 1) == (adapter._switch_attention is not Attention._switch_attention)
    assert (spec.flow_time is None) == issubclass(adapter, TokenObjective)
    assert issubclass(adapter, FlowObjective) or "_flow_losses" not in dir(adapter)  # no flow loss that only raises
    assert spec.steps_field is not None or adapter.num_steps is not Objective.num_steps
    assert all(n >= 1 for n in spec.cells_per_pass.values())


def test_a_class_naming_itself_a_backbone_elsewhere_or_without_a_spec_of_its_own_is_refused() -> None:
    """BackboneAdapter.__init_subclass__: the registry's rules hold as an adapter class is defined."""
    smolvla = get_backbone("smolvla")

    def define(qualname: str, module: str, **body) -> type:
        return types.new_class(qualname, (smolvla,), exec_body=lambda ns: ns.update(__module__=module, **body))

    with pytest.raises(BackboneError, match=r"is defined in graftcache\.backbones\.stray\.adapter"):
        define("Stray", "tests.elsewhere", name="stray", spec=smolvla.spec)
    with pytest.raises(BackboneError, match="declares no `spec` of its own"):
        define("Inherits", backbone_module("smolvla"), name="smolvla")
    assert define("Helper", "tests.elsewhere").spec is smolvla.spec  # no name of its own: not a registry entry
    assert smolvla.lerobot_type() == "smolvla"  # the registry name unless its spec names another lerobot type
