"""Every registered backbone end to end on the bundled LIBERO sample, in this process: `train-tiny`, `extract --encoder
<name>-native` (and a candidate encoder), then `fit` with every control. Few steps and a strided subset of
four episodes keep it cheap; what is checked is that each command runs the backbone's real code paths and
writes what the next one reads."""

from __future__ import annotations

import json
import math

import pytest
import torch
from fixtures.tiny_zoo import CONTROLS, TinyZoo

from graftcache import results
from graftcache.backbone_registry import BACKBONES
from graftcache.backbones import get_backbone
from graftcache.store import FeatureCache


@pytest.mark.slow  # ~1-2 min per backbone on 2 cores: 1 native step, two small extractions, 7 tiny fits
@pytest.mark.parametrize("name", sorted(BACKBONES))
def test_train_tiny_extract_native_and_fit_every_control(name: str, tiny_zoo: TinyZoo, capsys) -> None:
    """The commands run once per session in tests/fixtures/tiny_zoo.py (tests/export/test_export.py exports their
    cells). The native extraction stores what the trained policy's own tower and connector give (its grid before
    the connector, its tokens after), measured here on the policy loaded independently."""
    done = tiny_zoo.fitted(name, CONTROLS, capsys)
    adapter = get_backbone(name).load(done.policy)
    grid = adapter.token_grid
    policy, cache, table = done.policy, done.cache, done.table
    record = json.loads((policy / "graftcache_pretrain.json").read_text())
    assert record["backbone"] == name and record["cameras"] == ["image", "image2"]
    assert get_backbone(name).read_token_grid(policy) == grid

    native = done.native
    manifest = FeatureCache(cache / native.out.split()[-1]).manifest
    images = torch.rand(1, 3, manifest.encoder["image_size"], manifest.encoder["image_size"])
    assert list(manifest.encoder["grid"]) == list(adapter.native_patch_grid(images).shape[1:3])
    assert manifest.extras["connector"] == list(adapter.native_tokens(images).shape[1:])
    assert manifest.extras["connector"][-1] == adapter.lm_width
    # trained by train-tiny, not random-init: the manifest and the log say which (the rows keep the schema's True)
    assert (manifest.trained_by, manifest.random_init, manifest.weights["source"]) == ("train-tiny", False, "policy")
    assert f"encoder {name}-native is the tower of a policy trained by train-tiny ({policy})" in native.out
    assert "RANDOM-INIT" not in native.out

    rows = results.read(table)
    assert sorted(rows["control"]) == sorted(("none", *CONTROLS)) and set(rows["backbone"]) == {name}
    assert all(math.isfinite(v) and v > 0 for v in rows["eval_mse"])
    by_control = {r["control"]: r for r in rows.iter_rows(named=True)}
    assert by_control["native"]["encoder"] == f"{name}-native" and by_control["native"]["objective"] == "eval"
    assert by_control["native"]["encoder_random_init"] and by_control["native"]["backbone_random_init"]
    assert by_control["pool-2x2"]["pool_grid"] == "2x2" and by_control["none"]["pool_grid"] == f"{grid[0]}x{grid[1]}"
    assert by_control["lora"]["eval_mse"] != by_control["none"]["eval_mse"]  # the adapters trained too
