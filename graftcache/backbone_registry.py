"""The backbone registry: one folder per backbone, found by convention (data only: nothing here imports a backbone).

A backbone is a folder `graftcache/backbones/<name>/` holding (the registry's required pieces, `PIECES`):

- `adapter.py`: the one `graftcache.backbones.base.BackboneAdapter` subclass defined there whose `name` is <name>
  (graftcache.backbones.get_backbone finds it, as lerobot's policy factory finds a policy's classes by name);
- `spec.py`: `SPEC`, its `graftcache.backbones.spec.BackboneSpec`, the adapter's `spec`: data that imports neither
  torch nor lerobot, so a report reads labels and released sizes without importing any adapter
  (graftcache.backbones.registered_spec);
- `tiny.py`: `build_tiny(tiny, stats, device)`, its tiny configuration (graftcache.backbones.base.BackboneAdapter.load
  of "tiny" calls it).

Every place that names a backbone (the backbone loader, the native towers in the encoder catalog, the CLI's choices,
recipes) reads the names from `BACKBONES`, which lists the folders: adding a backbone is adding its folder (the
checklist: docs/ARCHITECTURE.md, "Adding a backbone"). The adapters themselves, which import lerobot, are imported only
when a backbone is used.
"""

from __future__ import annotations

from pathlib import Path

#: The files every backbone folder holds (tests/backbones/test_backbone_registry.py fails on a registered folder
#: lacking one).
PIECES = ("adapter", "spec", "tiny")
FOLDER = Path(__file__).resolve().parent / "backbones"


def backbone_module(name: str, piece: str = "adapter") -> str:
    """The dotted module of one piece of a backbone's folder, e.g. "graftcache.backbones.wall_x.tiny"."""
    return f"graftcache.backbones.{name}.{piece}"


def missing_pieces(folder: Path) -> list[str]:
    """The required pieces (`PIECES`) a backbone folder lacks, e.g. ["tiny"]."""
    return [piece for piece in PIECES if not (folder / f"{piece}.py").is_file()]


def discover(folder: Path) -> dict[str, str]:
    """Backbone name -> adapter module for every subfolder of `folder` that holds an adapter.py."""
    return {sub.name: backbone_module(sub.name) for sub in sorted(folder.iterdir()) if (sub / "adapter.py").is_file()}


#: Registered backbone name -> its adapter module: every folder of graftcache/backbones/ that holds an adapter.py.
BACKBONES: dict[str, str] = discover(FOLDER)

#: A backbone's own vision tower is the encoder `<backbone>-native` (stage 1 caches it like any encoder).
NATIVE_SUFFIX = "-native"


def native_name(backbone: str) -> str:
    """Registry name of a backbone's own vision tower, e.g. "smolvla-native"."""
    return f"{backbone}{NATIVE_SUFFIX}"


def backbone_of_native(encoder: str) -> str:
    """The backbone whose tower a native encoder name denotes ("smolvla-native" -> "smolvla")."""
    return encoder.removesuffix(NATIVE_SUFFIX)
