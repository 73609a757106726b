"""`fit --compile` (graftcache/backbones/compiled.py): the compiled training forward of a tiny random-init backbone
gives the eager loss and projector gradients (fp32, same draws), and undoing its patch puts the eager forward back.

CI compiles with torch's `aot_eager` backend (dynamo's graph capture and AOT autograd's forward/backward split, the
parts that decide what runs, without inductor's code generation) on the tiniest backbone with a compiled forward.
Inductor itself takes ~10 min on two contended CPU cores, so it runs only when asked: `GRAFTCACHE_TEST_INDUCTOR=1`
(it is skipped, saying why, where it cannot compile on the machine)."""

from __future__ import annotations

import os
import types

import pytest
import torch
from helpers.backbones import fixed_noise_time, grafted, raw_features

from graftcache.backbones import get_backbone
from graftcache.backbones.compiled import compile_forward
from graftcache.errors import BackboneError

#: Opt-in for the inductor case (minutes of C++ code generation on a CPU; the GPU check compiles with it anyway).
INDUCTOR = os.environ.get("GRAFTCACHE_TEST_INDUCTOR") == "1"


def _step(adapter, prepared: dict, noise: torch.Tensor, time: torch.Tensor) -> tuple[torch.Tensor, list]:
    params = [p for p in adapter.policy.parameters() if p.requires_grad]
    for p in params:
        p.grad = None
    loss = adapter.loss(prepared, noise=noise, time=time).mean()
    loss.backward()
    return loss.detach(), [p.grad.clone() for p in params]


@pytest.mark.parametrize(("name", "backend"), [
    ("pi0_fast", "aot_eager"),
    pytest.param("pi05", "inductor", marks=[pytest.mark.slow, pytest.mark.skipif(
        not INDUCTOR, reason="inductor compiles for ~10 min on CPU: set GRAFTCACHE_TEST_INDUCTOR=1 to run it")]),
])
def test_the_compiled_forward_gives_the_eager_loss_and_gradients(name: str, backend: str) -> None:
    adapter = grafted(name)
    adapter.policy.train()
    prepared, (noise, time) = adapter.prepare(raw_features(adapter, 2)), fixed_noise_time(adapter, 2)
    eager_loss, eager_grads = _step(adapter, prepared, noise, time)
    torch._dynamo.reset()
    patches = compile_forward(adapter, backend)
    try:
        loss, grads = _step(adapter, prepared, noise, time)
    except torch._dynamo.exc.BackendCompilerFailed as exc:
        pytest.skip(f"{backend} cannot compile on this machine: {str(exc).splitlines()[0][:200]}")
    finally:
        patches.undo()
    assert "forward" not in vars(adapter.policy.model)  # the class's eager forward shows through again
    assert len(grads) == len(eager_grads) and all(g.abs().sum() > 0 for g in grads)
    torch.testing.assert_close(loss, eager_loss, rtol=1e-5, atol=0)
    for got, want in zip(grads, eager_grads, strict=True):
        torch.testing.assert_close(got, want, rtol=1e-4, atol=1e-6)


def test_a_backbone_without_a_compiled_forward_is_refused_in_one_line() -> None:
    name = next(n for n in ("xvla", "groot", "eo1") if get_backbone(n).spec.compiled_forward is None)
    adapter = types.SimpleNamespace(name=name, spec=get_backbone(name).spec)  # what compile_forward reads
    with pytest.raises(BackboneError, match=rf"^{name}: no compiled forward for this backbone \(its spec names "
                       r"none\); drop --compile$"):
        compile_forward(adapter)
