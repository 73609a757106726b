"""The backbone registry's table: name -> adapter class, as import strings (data only).

Every place that names a backbone (the backbone loader, the native towers in the encoder catalog, the
CLI's choices, recipes) reads the names from here; the adapters themselves, which import lerobot, are
imported only when a backbone is used (graftcache.backbones.get_backbone).
"""

from __future__ import annotations

BACKBONES: dict[str, str] = {
    "smolvla": "graftcache.backbones.smolvla:SmolVLAAdapter",
    "pi05": "graftcache.backbones.pi05:PI05Adapter",
    "xvla": "graftcache.backbones.xvla:XVLAAdapter",
    "pi0": "graftcache.backbones.pi0:PI0Adapter",
    "pi0_fast": "graftcache.backbones.pi0_fast:PI0FastAdapter",
    "eo1": "graftcache.backbones.eo1:EO1Adapter",
    "evo1": "graftcache.backbones.evo1:Evo1Adapter",
    "groot": "graftcache.backbones.groot:GrootAdapter",
    "wall_x": "graftcache.backbones.wallx:WallXAdapter",
    "vla_jepa": "graftcache.backbones.vla_jepa:VLAJEPAAdapter",
}

#: Approximate parameter counts of the released policies (lerobot's docs), for results tables written before rows
#: recorded `backbone_params`: the analysis orders such a table's backbones by these, and says so in the report
#: (graftcache/analysis/ladder.py). Only their order matters; a backbone missing here needs the column.
RELEASED_PARAMS: dict[str, int] = {
    "smolvla": 450_000_000,
    "pi05": 3_300_000_000,
    "pi0": 3_300_000_000,
    "pi0_fast": 2_900_000_000,
}

#: A backbone's own vision tower is the encoder `<backbone>-native` (stage 1 caches it like any encoder).
NATIVE_SUFFIX = "-native"


def native_name(backbone: str) -> str:
    """Registry name of a backbone's own vision tower, e.g. "smolvla-native"."""
    return f"{backbone}{NATIVE_SUFFIX}"


def backbone_of_native(encoder: str) -> str:
    """The backbone whose tower a native encoder name denotes ("smolvla-native" -> "smolvla")."""
    return encoder.removesuffix(NATIVE_SUFFIX)
