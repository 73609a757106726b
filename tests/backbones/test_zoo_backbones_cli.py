"""The zoo backbones end to end on the bundled LIBERO sample, in this process: `train-tiny`, `extract --encoder
<name>-native` (and a candidate encoder), then `fit` with every control. Few steps and a strided subset of
four episodes keep it cheap; what is checked is that each command runs the backbone's real code paths and
writes what the next one reads."""

from __future__ import annotations

import json
import math

import pytest
from fixtures.tiny_zoo import CONTROLS, TinyZoo

from graftcache import results
from graftcache.backbones import get_backbone
from graftcache.store import FeatureCache

#: backbone -> (native token grid, the tower's own grid before its connector, post-connector tokens per camera, LM
#: width) of its tiny configuration (the Qwen ViTs of EO-1, GR00T, Wall-X and VLA-JEPA, and EVO1's InternViT: 8x8
#: patches, merged 2x2 by their connectors)
TINY = {"xvla": ((4, 4), (4, 4), 17, 64), "pi0": ((4, 4), (4, 4), 16, 128), "pi0_fast": ((4, 4), (4, 4), 16, 128),
        "eo1": ((4, 4), (8, 8), 16, 64), "evo1": ((4, 4), (8, 8), 16, 64), "groot": ((4, 4), (8, 8), 16, 64),
        "wall_x": ((4, 4), (8, 8), 16, 64), "vla_jepa": ((4, 4), (8, 8), 16, 64)}


@pytest.mark.slow  # ~1-2 min per backbone on 2 cores: 1 native step, two small extractions, 7 tiny fits
@pytest.mark.parametrize("name", sorted(TINY))
def test_train_tiny_extract_native_and_fit_every_control(name: str, tiny_zoo: TinyZoo, capsys) -> None:
    """The commands run once per session in tests/fixtures/tiny_zoo.py (tests/export/test_export.py exports their cells)."""
    grid, tower_grid, tokens, width = TINY[name]
    done = tiny_zoo.fitted(name, CONTROLS, capsys)
    policy, cache, table = done.policy, done.cache, done.table
    record = json.loads((policy / "graftcache_pretrain.json").read_text())
    assert record["backbone"] == name and record["cameras"] == ["image", "image2"]
    assert get_backbone(name).read_token_grid(policy) == grid

    native = done.native
    manifest = FeatureCache(cache / native.out.split()[-1]).manifest
    assert tuple(manifest.encoder["grid"]) == tower_grid and manifest.extras["connector"] == [tokens, width]

    rows = results.read(table)
    assert sorted(rows["control"]) == sorted(("none", *CONTROLS)) and set(rows["backbone"]) == {name}
    assert all(math.isfinite(v) and v > 0 for v in rows["eval_mse"])
    by_control = {r["control"]: r for r in rows.iter_rows(named=True)}
    assert by_control["native"]["encoder"] == f"{name}-native" and by_control["native"]["objective"] == "eval"
    assert by_control["pool-2x2"]["pool_grid"] == "2x2" and by_control["none"]["pool_grid"] == f"{grid[0]}x{grid[1]}"
    assert by_control["lora"]["eval_mse"] != by_control["none"]["eval_mse"]  # the adapters trained too
