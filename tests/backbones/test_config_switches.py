"""A released checkpoint's own config switches never change how graftcache computes behind its back: lerobot's
torch.compile of forward / sample_actions (`compile_model`), its gradient checkpointing (`gradient_checkpointing`,
EVO1's `enable_gradient_checkpointing`), EVO1's bf16 autocast on CUDA (`use_amp`) and GR00T's bf16 autocast
(`use_bf16`) are neutralised at load (graftcache.backbones.base.NEUTRAL_CONFIG, GrootAdapter's autocast), so rows'
`activation_checkpointing` and `compute_dtype` say what ran. Tiny checkpoints whose configs set them stand in for
the public fine-tunes that do."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from helpers.backbones import ENC_DIM, backbones_where, fixed_noise_time, raw_features, tiny
from torch import nn

from graftcache.backbones import BACKBONES, get_backbone
from graftcache.backbones.base import BackboneAdapter
from graftcache.graft import GraftProjector

BATCH = 2


def _saved_with(name: str, folder: Path, **switches: object) -> Path:
    """A tiny `name` checkpoint whose config.json sets `switches`."""
    tiny(name).save(folder)
    config = json.loads((folder / "config.json").read_text())
    assert set(switches) <= set(config), sorted(set(switches) - set(config))  # lerobot's own field names
    (folder / "config.json").write_text(json.dumps({**config, **switches}))
    return folder


def _compiled(policy: nn.Module) -> list[str]:
    """Methods that torch.compile has wrapped on the policy's modules."""
    return [f"{module}.{attr}" for module, m in policy.named_modules() for attr, value in vars(m).items()
            if hasattr(value, "_torchdynamo_orig_callable")]


def _checkpointing(policy: nn.Module) -> list[str]:
    """Modules whose own gradient-checkpointing flag is on (lerobot's and transformers')."""
    flags = ("gradient_checkpointing", "gradient_checkpointing_enabled")
    return [module for module, m in policy.named_modules() if any(getattr(m, flag, False) is True for flag in flags)]


def _wrapped(policy: nn.Module) -> list[int]:
    """ids of graftcache's activation checkpointing wrappers
    (graftcache.backbones.activation_checkpointing.checkpointed) on the policy."""
    return [id(value) for m in policy.modules() for value in vars(m).values()
            if getattr(value, "__qualname__", "") == "checkpointed.<locals>.run"]


#: The switches that compile the policy or checkpoint its activations under lerobot's own names (EVO1's: below).
COMPILE_AND_CHECKPOINTING = ("compile_model", "gradient_checkpointing")


def _config_fields(name: str) -> set[str]:
    """The fields of the lerobot config class of the policy backbone `name` wraps."""
    import dataclasses

    import lerobot.policies  # noqa: F401  (its __init__ registers every policy's config type)
    from lerobot.configs.policies import PreTrainedConfig

    return {f.name for f in dataclasses.fields(PreTrainedConfig.get_choice_class(get_backbone(name).lerobot_type()))}


@pytest.mark.parametrize("name", sorted(BACKBONES))
def test_compile_and_gradient_checkpointing_of_a_checkpoint_s_config_are_off_after_load(
        name: str, tmp_path: Path) -> None:
    """Every backbone whose lerobot config has the switches (SmolVLA: compile; the PaliGemma policies: both; EO-1:
    checkpointing), each set on."""
    switches = dict.fromkeys(sorted(_config_fields(name) & set(COMPILE_AND_CHECKPOINTING)), True)
    if not switches:
        pytest.skip(f"{name}'s lerobot config has neither {' nor '.join(COMPILE_AND_CHECKPOINTING)}")
    adapter = get_backbone(name).load(_saved_with(name, tmp_path / "policy", **switches))
    assert _compiled(adapter.policy) == []
    assert _checkpointing(adapter.policy) == []
    assert adapter.recomputing is False


def test_evo1_s_amp_and_checkpointing_switches_are_off_after_load(tmp_path: Path,
                                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    """EVO1 wraps its passes in bf16 autocast on CUDA whatever --compute-dtype says (use_amp); on CUDA graftcache's
    own autocast decides instead."""
    folder = _saved_with("evo1", tmp_path / "policy", use_amp=True, enable_gradient_checkpointing=True)
    adapter = get_backbone("evo1").load(folder)
    monkeypatch.setattr(type(adapter.policy), "_device", property(lambda self: torch.device("cuda")))
    assert adapter.policy._amp_enabled is False
    assert _checkpointing(adapter.policy) == []
    assert tiny("evo1").policy._amp_enabled is False  # the tiny config's default is True


def test_groot_computes_in_the_callers_dtype_whatever_use_bf16_says(tmp_path: Path) -> None:
    """GR00T opens autocast(bf16, enabled=use_bf16) around its forward: on, a fit in fp32 ran in bf16; off, a fit
    in bf16 ran in fp32. Either way the loss is the one of the caller's own autocast."""
    losses = {}
    for use_bf16 in (False, True):
        adapter = get_backbone("groot").load(_saved_with("groot", tmp_path / f"p{use_bf16}", use_bf16=use_bf16),
                                             device="cpu")
        torch.manual_seed(0)
        adapter.graft(GraftProjector(ENC_DIM, adapter.lm_width))
        adapter.policy.eval()
        batch = adapter.prepare(raw_features(adapter, BATCH))
        noise, time = fixed_noise_time(adapter, BATCH)
        with torch.no_grad():
            fp32 = adapter.loss(batch, noise=noise, time=time)
            with torch.autocast("cpu", dtype=torch.bfloat16):
                bf16 = adapter.loss(batch, noise=noise, time=time)
        losses[use_bf16] = fp32, bf16
    torch.testing.assert_close(losses[True][0], losses[False][0], rtol=0, atol=0)
    torch.testing.assert_close(losses[True][1], losses[False][1], rtol=0, atol=0)
    assert not torch.equal(losses[False][0], losses[False][1])  # bf16 computes something else: it did run


@pytest.mark.parametrize("name", backbones_where(lambda spec: spec.can_recompute))
def test_checkpointing_off_turns_off_the_policy_s_own_too(name: str) -> None:
    """`set_recompute(False)` makes the model agree with the flag rows record, whatever turned the
    model's own checkpointing on (lerobot's switch, a second `on`), and on, off, on, off leaves no layer wrapped."""
    adapter: BackboneAdapter = tiny(name)
    switch = getattr(type(adapter.policy.model), "gradient_checkpointing_enable", None)
    own_switch = switch is not None and switch.__module__.startswith("lerobot.")  # lerobot's own (PaliGemma policies')
    if own_switch:
        adapter.policy.model.gradient_checkpointing_enable()  # lerobot's own, behind graftcache's back
    torch.manual_seed(0)
    adapter.graft(GraftProjector(ENC_DIM, adapter.lm_width))
    if own_switch:
        assert _checkpointing(adapter.policy)
        adapter.set_recompute(False)
        assert _checkpointing(adapter.policy) == []
    wrapped = []
    for on in (True, True, False, False, True, False):
        adapter.set_recompute(on)
        assert adapter.recomputing is on
        wrapped.append(_wrapped(adapter.policy))
    assert _checkpointing(adapter.policy) == []
    assert wrapped[1] == wrapped[0] and wrapped[2] == wrapped[3] == wrapped[5] == []  # a second on wraps nothing twice
