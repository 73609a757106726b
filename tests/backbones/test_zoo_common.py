"""Checks the Qwen/InternVL backbones (EO-1, GR00T, Wall-X, VLA-JEPA, EVO1) pass the same way, with per-backbone
facts as a row of `ZOO`: a missing base repo is a one-line error, LoRA sits where each LM's decoder layers are and
reset takes it and the graft's shadows away, the loss masks padded steps per sample, and the native control
reproduces the ungrafted policy. Loading by hub id, lean load, LoRA inside the language model and reset for every
backbone: tests/backbones/test_contract.py."""

from __future__ import annotations

import json
from dataclasses import dataclass

import pytest
import torch
from helpers.backbones import (
    ENC_DIM,
    TINY_SIZE,
    assert_native_control_reproduces,
    fixed_noise_time,
    raw_images,
    tiny,
)

from graftcache.backbones import load_backbone
from graftcache.backbones.checkpoint import state_dict_sha256
from graftcache.errors import BackboneError
from graftcache.graft import GraftProjector


@dataclass(frozen=True)
class Zoo:
    """How one backbone's tiny policy answers the shared checks."""

    lora_prefix: str                     # where every LoRA parameter lives: the LM's decoder layers
    frozen: tuple[str, ...]              # freeze-report rows LoRA leaves untrained
    base_key: str = ""                   # the config field naming the base repo ("": checked in its own file)
    base_repo: str = ""                  # a released base repo, absent from an empty HF cache
    base_error: str = ""                 # the one-line error naming it
    lora_also: str = ""                  # a part some LoRA parameter must sit in
    shadows: tuple[str, ...] = ()        # instance attributes the graft shadows on the policy and reset removes
    masked_mean: bool = False            # the loss is the mean of `_flow_losses` over real steps and dims
    native_control: bool = False         # the generic native control (deepstack backbones test theirs in their file)


ZOO = {
    "eo1": Zoo("model.vlm_backbone.model.language_model.layers.", ("action head", "patch embedding"),
               "vlm_base", "Qwen/Qwen2.5-VL-3B-Instruct",
               "EO-1's Qwen2.5-VL processor 'Qwen/Qwen2.5-VL-3B-Instruct' is neither", masked_mean=True,
               native_control=True),
    "groot": Zoo("_groot_model.backbone.model.model.language_model.layers.", ("action head", "patch embedding"),
                 masked_mean=True),
    "wall_x": Zoo("model.model.layers.", ("action head", "patch embedding"),
                  "pretrained_name_or_path", "x-square-robot/wall-oss-flow",
                  "Wall-X's base config and processor 'x-square-robot/wall-oss-flow' is neither",
                  lora_also=".moe.experts.1.",  # the action expert's MLP is adapted too
                  masked_mean=True, native_control=True),
    "vla_jepa": Zoo("model.qwen.model.model.language_model.layers.", ("action head", "deepstack mergers"),
                    "qwen_model_name", "Qwen/Qwen3-VL-2B-Instruct",
                    "VLA-JEPA's Qwen3-VL config and processor 'Qwen/Qwen3-VL-2B-Instruct' is neither a local folder "
                    "nor in the Hugging Face cache"),
    "evo1": Zoo("model.embedder.model.language_model.layers.", ("action head",),
                "vlm_model_name", "OpenGVLab/InternVL3-1B-hf",
                "InternVL config and tokenizer 'OpenGVLab/InternVL3-1B-hf' is neither",
                shadows=("_compute_fused_tokens",), native_control=True),
}


@pytest.mark.parametrize("name", [n for n, zoo in ZOO.items() if zoo.base_key])
def test_missing_base_repo_is_one_line(name: str, tmp_path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A (non-tiny) checkpoint whose base repo (config, processor or tokenizer) is not in the HF cache: one line
    naming it."""
    zoo = ZOO[name]
    folder = tiny(name).save(tmp_path / "policy")
    (folder / "graftcache_tiny.json").unlink()
    config = json.loads((folder / "config.json").read_text())
    (folder / "config.json").write_text(json.dumps({**config, zoo.base_key: zoo.base_repo}))
    monkeypatch.setenv("HF_HUB_CACHE", str(tmp_path / "empty"))
    with pytest.raises(BackboneError, match=zoo.base_error):
        load_backbone(name, folder)


@pytest.mark.parametrize("name", list(ZOO))
def test_lora_adapts_the_language_model_and_reset_restores_the_policy(name: str) -> None:
    zoo = ZOO[name]
    adapter = tiny(name)
    sha = adapter.policy_sha256
    images = torch.rand(1, 3, TINY_SIZE, TINY_SIZE)
    before = adapter.native_tokens(images)
    adapter.graft(GraftProjector(ENC_DIM, adapter.lm_width))
    adapter.add_lora(4)
    lora = {n for n, p in adapter.policy.named_parameters() if p.requires_grad and "lora_" in n}
    assert lora and all(n.startswith(zoo.lora_prefix) for n in lora)
    assert not zoo.lora_also or any(zoo.lora_also in n for n in lora)
    report = {r.module: r for r in adapter.freeze_report().rows}
    assert all(report[row].trainable == 0 for row in zoo.frozen)
    assert report["vision tower"].params == 0  # the pass-through
    assert 0 < report["language model"].trainable < report["language model"].params
    adapter.reset()
    assert not adapter.grafted and state_dict_sha256(adapter.policy) == sha
    assert not set(zoo.shadows) & set(adapter.policy.__dict__)
    torch.testing.assert_close(adapter.native_tokens(images), before)  # the tower is back


@pytest.mark.parametrize("name", [n for n, zoo in ZOO.items() if zoo.masked_mean])
def test_loss_masks_padded_steps_and_padded_dims_per_sample(name: str) -> None:
    """The per-sample loss is the mean error over the sample's real steps and the dataset's 7 action dims (the
    first sample's last 3 steps are padding: helpers.backbones.raw_lowdim)."""
    adapter = tiny(name)
    adapter.policy.eval()
    batch = adapter.prepare(raw_images(adapter, 3, size=TINY_SIZE))
    noise, time = fixed_noise_time(adapter, 3)
    with torch.no_grad():
        error = adapter._flow_losses(batch, noise, time)[:, :, :7]
        loss = adapter.loss(batch, noise, time)
    torch.testing.assert_close(loss, torch.stack([error[0, :-3].mean(), error[1].mean(), error[2].mean()]))


@pytest.mark.parametrize("name", [n for n, zoo in ZOO.items() if zoo.native_control])
def test_native_control_reproduces_the_ungrafted_policy(name: str) -> None:
    """(GR00T and VLA-JEPA have deepstack features a graft drops: their files test the control without them.)"""
    assert_native_control_reproduces(tiny(name), tiny(name), 3, size=TINY_SIZE)
