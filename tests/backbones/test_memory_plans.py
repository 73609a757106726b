"""Recompute plans (graftcache.backbones.activation_checkpointing.PLANS): every plan a backbone has trains with the loss
and projector gradients of keeping every activation (fp32, tiny random-init backbones, same draws); going back to
`off` undoes every change a plan made; `auto` (graftcache/fit/step_memory.py) takes the plan that recomputes least
among those whose measured step fits the device's memory, here a fake budget."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from helpers.backbones import fixed_noise_time, grafted, raw_features

from graftcache.backbones import BACKBONES, get_backbone
from graftcache.backbones.activation_checkpointing import PLANS, ActivationCheckpointing
from graftcache.backbones.patching import observe
from graftcache.budget import BudgetError
from graftcache.errors import BackboneError
from graftcache.fit import step_memory
from graftcache.fit.data import LowDim
from graftcache.fit.step_bytes import saved_bytes

#: The backbones with an `mlp` plan (those declaring `_mlp_slots`): every plan of PLANS.
WITH_MLP = [n for n in sorted(BACKBONES) if get_backbone(n)._mlp_slots is not ActivationCheckpointing._mlp_slots]


def test_the_released_size_backbones_have_every_plan() -> None:
    assert {"pi05", "pi0", "pi0_fast", "smolvla"} <= set(WITH_MLP)
    assert tuple(PLANS) == ("off", "mlp", "on")  # least recompute first: what `auto` walks


def _step(adapter, prepared: dict, noise: torch.Tensor, time: torch.Tensor) -> tuple[torch.Tensor, list]:
    params = [p for p in adapter.policy.parameters() if p.requires_grad]
    for p in params:
        p.grad = None
    torch.manual_seed(0)  # the same dropout masks, if any
    loss = adapter.loss(prepared, noise=noise, time=time).mean()
    loss.backward()
    return loss.detach(), [p.grad.clone() for p in params]


@pytest.mark.parametrize("name", WITH_MLP)
def test_every_plan_keeps_the_loss_and_gradients_and_off_undoes_it(name: str) -> None:
    adapter = grafted(name)
    assert adapter.recompute_plans == ("off", "mlp", "on") and adapter.recompute_plan == "off"
    adapter.policy.train()
    raw = raw_features(adapter, 3)
    prepared, (noise, time) = adapter.prepare(dict(raw)), fixed_noise_time(adapter, 3)
    plain_loss, plain_grads = _step(adapter, prepared, noise, time)
    kept = {"off": saved_bytes(adapter, raw, 3, torch.float32)}
    for plan in ("mlp", "on"):
        with observe() as changes:
            adapter.set_recompute_plan(plan)
            assert adapter.recompute_plan == plan and adapter.recomputing
            loss, grads = _step(adapter, prepared, noise, time)
            kept[plan] = saved_bytes(adapter, raw, 3, torch.float32)
            adapter.set_recompute_plan("off")
        assert not adapter.recomputing
        torch.testing.assert_close(loss, plain_loss, rtol=1e-6, atol=0)
        assert len(grads) == len(plain_grads) and all(g.abs().sum() > 0 for g in grads)
        for got, want in zip(grads, plain_grads, strict=True):
            torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-7)
        assert all(change.is_restored() for change in changes)
        if plan == "mlp":  # one wrapper per LM and expert layer's MLP, each undone
            assert len(changes) == len(list(adapter._mlp_slots())) > 0
            assert {c.attribute for c in changes} == {"forward"}
    # what autograd keeps for backward: the MLPs' activations leave it under mlp, whole layers' under on
    assert kept["on"] <= kept["mlp"] < kept["off"], kept


def test_a_plan_the_backbone_lacks_is_refused_in_one_line() -> None:
    name = next(n for n in sorted(BACKBONES) if n not in WITH_MLP and get_backbone(n).spec.can_recompute)
    adapter = grafted(name)
    assert adapter.recompute_plans == ("off", "on")
    with pytest.raises(BackboneError, match=rf"^{name}: no recompute plan 'mlp' for this backbone; use "
                       r"--recompute off or on$"):
        adapter.set_recompute_plan("mlp")
    assert adapter.recompute_plan == "off"


class _Source:
    """What check_step_memory reads of a feature source: a frame's shape per camera and its stored bytes."""

    def __init__(self, tokens: int, width: int) -> None:
        self.tokens, self.width = tokens, width

    def frame_shape(self, cam: str) -> tuple[int, int]:
        return self.tokens, self.width

    def frame_bytes(self) -> int:
        return self.tokens * self.width * 2


def _low(adapter, frames: int = 4) -> LowDim:
    chunk, steps = adapter.chunk_size, frames + adapter.chunk_size
    return LowDim(rows=np.arange(frames), index=np.arange(frames), episode_index=np.zeros(frames, dtype=np.int64),
                  frame_index=np.arange(frames), state=torch.zeros(frames, adapter.state_dim),
                  task_index=torch.zeros(frames, dtype=torch.int64), stream_start=np.arange(frames),
                  stream_end=np.full(frames, steps), actions=torch.zeros(steps, adapter.action_dim), chunk=chunk,
                  tasks=("put the bowl on the plate",), critical=np.zeros(steps, dtype=bool))


def test_auto_takes_the_plan_that_recomputes_least_among_those_that_fit(monkeypatch: pytest.MonkeyPatch) -> None:
    """Each plan's need is what check_step_memory measures under it; with the device's budget set between two
    plans' needs, auto takes the one that fits and recomputes least, and below every need it refuses in one line
    naming the plan that keeps least."""
    adapter = grafted("pi05")
    cams = {cam: "agentview" for cam in adapter.cameras}
    source, low = _Source(adapter.token_grid[0] * adapter.token_grid[1], 48), _low(adapter)
    kwargs = {"batch_size": 4096, "buffer_mib": 1, "dtype": torch.float32}
    needs: dict[str, int] = {}
    monkeypatch.setattr(step_memory, "require", lambda what, need, have, limit, hint: needs.update({plan: need}))
    for plan in adapter.recompute_plans:
        assert step_memory.check_step_memory(adapter, low, cams, source, recompute=plan, **kwargs) == plan
    assert needs["off"] > needs["mlp"] > needs["on"] > 0, needs
    monkeypatch.undo()
    for expected, budget in (("mlp", (needs["off"] + needs["mlp"]) // 2), ("on", (needs["mlp"] + needs["on"]) // 2)):
        monkeypatch.setattr(step_memory, "available_memory", lambda device, b=budget: (b, "the fake budget"))
        assert step_memory.check_step_memory(adapter, low, cams, source, recompute="auto", **kwargs) == expected
        assert adapter.recompute_plan == expected
    monkeypatch.setattr(step_memory, "available_memory", lambda device: (needs["on"] - 1, "the fake budget"))
    with pytest.raises(BudgetError, match=r"^a training step of --batch-size 4096 with activation checkpointing \(.*"
                       r"the fake budget is .*; lower --batch-size$"):
        step_memory.check_step_memory(adapter, low, cams, source, recompute="auto", **kwargs)
    with pytest.raises(BudgetError, match=r"^a training step of --batch-size 4096 with activation checkpointing of "
                       r"each layer's MLP \(.*; lower --batch-size or pass --recompute on$"):
        step_memory.check_step_memory(adapter, low, cams, source, recompute="mlp", **kwargs)
