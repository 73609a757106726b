"""The backbone registry is the folders of graftcache/backbones/: every registered backbone has every required piece
(graftcache.backbone_table.PIECES: its adapter class, its tiny configuration), found by convention."""

from __future__ import annotations

import dataclasses
import inspect
import types
from importlib import import_module
from pathlib import Path

import pytest

from graftcache.backbone_table import BACKBONES, FOLDER, PIECES, backbone_module, discover, missing_pieces
from graftcache.backbones import get_backbone, registered_spec
from graftcache.backbones.activation_checkpointing import ActivationCheckpointing
from graftcache.backbones.attention import Attention
from graftcache.backbones.base import BackboneAdapter
from graftcache.backbones.objectives import FlowObjective, Objective, TokenObjective
from graftcache.backbones.spec import BackboneSpec
from graftcache.errors import BackboneError


def test_the_registry_lists_the_folders_holding_an_adapter(tmp_path: Path) -> None:
    """Discovery on a made-up package folder: a folder with an adapter.py is a backbone, whatever else it lacks
    (the next test names its missing pieces); a folder without one, a module and a cache folder are not."""
    for folder, files in {"alpha": ("adapter.py",), "beta": ("adapter.py", "spec.py", "tiny.py"),
                          "shared": ("tiny.py",), "__pycache__": ("adapter.cpython-313.pyc",)}.items():
        (tmp_path / folder).mkdir()
        for name in files:
            (tmp_path / folder / name).write_text("")
    (tmp_path / "adapter.py").write_text("")
    assert discover(tmp_path) == {"alpha": "graftcache.backbones.alpha.adapter",
                                  "beta": "graftcache.backbones.beta.adapter"}
    assert {"smolvla", "pi05"} <= set(BACKBONES) and "tiny" not in BACKBONES  # the package's own: folders, not modules


def test_a_folder_lacking_a_piece_is_named(tmp_path: Path) -> None:
    (tmp_path / "adapter.py").write_text("")
    assert missing_pieces(tmp_path) == [p for p in PIECES if p != "adapter"]


@pytest.mark.parametrize("name", sorted(BACKBONES))
def test_every_registered_backbone_has_every_piece(name: str) -> None:
    assert missing_pieces(FOLDER / name) == [], f"graftcache/backbones/{name}/ lacks a required piece"
    adapter = get_backbone(name)
    assert issubclass(adapter, BackboneAdapter) and not inspect.isabstract(adapter), adapter.__abstractmethods__
    assert adapter.spec is registered_spec(name)  # what reports read without the adapter is what it runs with
    assert callable(import_module(backbone_module(name, "tiny")).build_tiny)


@pytest.mark.parametrize("name", sorted(BACKBONES))
def test_every_registered_backbone_declares_a_spec_its_hooks_agree_with(name: str) -> None:
    adapter = get_backbone(name)
    spec = adapter.spec
    assert isinstance(spec, BackboneSpec)
    assert spec.can_recompute == (
        adapter._switch_recompute is not ActivationCheckpointing._switch_recompute)
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
    with pytest.raises(BackboneError, match=r"its `spec` is not graftcache\.backbones\.smolvla\.spec\.SPEC"):
        define("Inherits", backbone_module("smolvla"), name="smolvla")
    with pytest.raises(BackboneError, match=r"its `spec` is not graftcache\.backbones\.smolvla\.spec\.SPEC"):
        define("Copied", backbone_module("smolvla"), name="smolvla", spec=dataclasses.replace(smolvla.spec))
    assert define("Helper", "tests.elsewhere").spec is smolvla.spec  # no name of its own: not a registry entry
    assert smolvla.lerobot_type() == "smolvla"  # the registry name unless its spec names another lerobot type
