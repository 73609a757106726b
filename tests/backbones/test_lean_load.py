"""Lean loading's refusals (a mis-shaped or cut-short checkpoint) and the undo of a graft refusing a frozen weight
written meanwhile. Lean load = lerobot's from_pretrained and reset = a fresh load, bit for bit, for every backbone:
the contract (tests/backbones/test_contract.py); a config asking for bf16: tests/backbones/test_pi05.py."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import torch
from helpers.backbones import ENC_DIM, tiny

from graftcache.backbones import load_backbone
from graftcache.backbones.lean_load import read_into
from graftcache.errors import BackboneError
from graftcache.graft import GraftProjector

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # tests/fixtures/torch_threads.py


def test_a_mis_shaped_or_cut_short_checkpoint_is_refused_by_name(tmp_path: Path) -> None:
    from safetensors.torch import load_file, save_file

    folder = tiny("smolvla").save(tmp_path / "ckpt")
    path = folder / "model.safetensors"
    weights = load_file(path)
    key = next(k for k in weights if k.endswith("action_out_proj.weight"))
    weights[key] = weights[key][:, :-1].contiguous()
    save_file(weights, path)
    with pytest.raises(BackboneError, match=rf"0 missing, 1 mis-shaped.*shape {key} \(8, \d+\) vs \(8, \d+\)"):
        load_backbone("smolvla", folder)
    path.write_bytes(path.read_bytes()[:-100])  # caught with the header, before anything is built
    with pytest.raises(BackboneError, match=rf"{re.escape(str(path))}: not a safetensors file"):
        load_backbone("smolvla", folder)
    with path.open("rb", buffering=0) as f, pytest.raises(BackboneError, match=rf"{re.escape(str(path))}: trunc"):
        read_into(f, path.stat().st_size - 8, torch.empty(4))  # a file cut after its header was read


def test_a_frozen_weight_written_while_grafted_is_an_error_at_reset() -> None:
    adapter = tiny("smolvla")
    adapter.graft(GraftProjector(ENC_DIM, adapter.lm_width))
    with torch.no_grad():
        adapter.policy.model.state_proj.weight.add_(1.0)
    with pytest.raises(BackboneError, match=r"1 frozen policy tensors were written.*state_proj\.weight.*reload"):
        adapter.reset()
