"""The fused attention path (graftcache/backbones/attention.py) computes what lerobot's eager path computes: under the
same weights and draws, every backbone with two paths gives the same training loss, projector gradients and predicted
chunk with either, within attention.TOLERANCE of the resolved compute dtype; and switching back gives lerobot every
object it had."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import pytest
import torch
from helpers.backbones import backbones_where, fixed_noise_time, grafted, raw_features
from transformers.models.gemma import modeling_gemma

from graftcache.backbones import BACKBONES, get_backbone
from graftcache.backbones.attention import EAGER, FUSED, TOLERANCE
from graftcache.backbones.paligemma import FUSED_MARK, GemmaAttentionForward
from graftcache.backbones.patching import observe
from graftcache.errors import BackboneError
from graftcache.runtime import autocast, resolve_compute_dtype, resolve_dtype

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # tests/fixtures/torch_threads.py

TWO_PATHS = backbones_where(lambda spec: len(spec.attentions) > 1)


def _difference(reference: torch.Tensor, other: torch.Tensor) -> float:
    """|other - reference| / |reference| over the whole tensor (attention.TOLERANCE's measure)."""
    reference, other = reference.double(), other.double()
    return float((other - reference).norm() / reference.norm())


@contextlib.contextmanager
def _counted_sdpa() -> Iterator[list[int]]:
    """torch's scaled_dot_product_attention, its calls counted ([n]) while the block runs."""
    sdpa, calls = torch.nn.functional.scaled_dot_product_attention, [0]

    def counted(*args, **kwargs):
        calls[0] += 1
        return sdpa(*args, **kwargs)

    torch.nn.functional.scaled_dot_product_attention = counted
    try:
        yield calls
    finally:
        torch.nn.functional.scaled_dot_product_attention = sdpa


def _step_and_chunk(adapter, mode: str, dtype: torch.dtype) -> dict[str, torch.Tensor]:
    """One training step's loss and projector gradients and the predicted chunk, attending with `mode`, under the
    fit's autocast of `dtype`, with fixed draws; the kernel is called only on the fused path (the grafted policy has
    no vision tower left to call it)."""
    assert adapter.set_attention(mode) == mode == adapter.attention
    batch = adapter.prepare(raw_features(adapter, 2))
    noise, time = fixed_noise_time(adapter, 2)
    adapter.policy.train()
    adapter.projector.zero_grad(set_to_none=True)
    with _counted_sdpa() as calls:
        with autocast(torch.device("cpu"), dtype):
            loss = adapter.loss(batch, noise, time)
        loss.sum().backward()
        with torch.no_grad(), autocast(torch.device("cpu"), dtype):
            chunk = adapter.predict(batch, noise)
    assert (calls[0] > 0) == (mode == FUSED), calls
    grads = torch.cat([p.grad.flatten() for p in adapter.projector.parameters()])
    return {"loss": loss.detach(), "projector gradients": grads, "predicted chunk": chunk}


@pytest.mark.parametrize("name", TWO_PATHS)
def test_the_fused_path_gives_eagers_loss_gradients_and_chunk(name: str, auto_resolution: str) -> None:
    """Both paths in both resolutions of `auto` (fp32; bf16 autocast), within TOLERANCE of that dtype; eager's own
    numbers move further than that between fp32 and bf16, so the test can tell a wrong kernel from rounding. Where
    the backbone recomputes activations, the fused path while recomputing gives the same gradients too (the
    switch turns recompute off around itself and back on)."""
    adapter = grafted(name)
    dtype = resolve_dtype(resolve_compute_dtype("auto", "cpu"))
    eager, fused = (_step_and_chunk(adapter, mode, dtype) for mode in (EAGER, FUSED))
    for what, value in eager.items():
        assert torch.isfinite(value).all() and value.abs().max() > 0, what
        assert _difference(value, fused[what]) <= TOLERANCE[auto_resolution], what
    if adapter.spec.can_recompute:
        adapter.set_recompute(True)
        checkpointed = _step_and_chunk(adapter, FUSED, dtype)
        assert adapter.recomputing
        assert _difference(fused["projector gradients"], checkpointed["projector gradients"]) <= 1e-6
        adapter.set_recompute(False)


def test_the_tolerance_tells_a_wrong_attention_from_rounding(monkeypatch: pytest.MonkeyPatch) -> None:
    """A fused kernel that scales the scores by 1.1 times the head's factor is caught in fp32: its loss, gradients or
    chunk are further from eager's than TOLERANCE allows (a tiny random-init model attends almost uniformly, so
    the check is not strong for bf16, whose tolerance is its rounding's)."""
    from graftcache.backbones.smolvla import adapter as smolvla

    adapter = grafted("smolvla")
    eager = _step_and_chunk(adapter, EAGER, torch.float32)
    right = smolvla.fused_attention
    monkeypatch.setattr(smolvla, "fused_attention", lambda q, k, v, mask, scaling: right(q, k, v, mask, 1.1 * scaling))
    wrong = _step_and_chunk(adapter, FUSED, torch.float32)
    assert max(_difference(eager[what], wrong[what]) for what in eager) > 10 * TOLERANCE["fp32"]


@pytest.mark.parametrize("name", TWO_PATHS)
def test_switching_back_gives_lerobot_every_object_it_had(name: str) -> None:
    """To the other path and back: every change recorded and undone to the very object it replaced, modeling_gemma's
    eager function among them, and no GemmaAttention keeps a mark."""
    adapter = grafted(name)
    eager_function = modeling_gemma.eager_attention_forward
    own, other = adapter.spec.attentions[:2]
    with observe() as changes:
        adapter.set_attention(other)
        assert adapter.attention == other and changes
        adapter.set_attention(own)
    assert adapter.attention == own and not adapter.attention_patches.changes
    assert [(c.owner, c.attribute) for c in changes if not c.is_restored()] == []
    assert modeling_gemma.eager_attention_forward is eager_function
    assert not any(hasattr(m, FUSED_MARK) for m in adapter.policy.modules())


def test_a_fused_policy_leaves_another_policys_gemma_eager() -> None:
    """pi0 and pi0.5 share modeling_gemma's module global: pi0.5 attending fused leaves pi0's loss, attending eager,
    exactly what it was."""
    pi0 = grafted("pi0")
    before = _step_and_chunk(pi0, EAGER, torch.float32)["loss"]
    pi05 = grafted("pi05")
    pi05.set_attention(FUSED)
    assert isinstance(modeling_gemma.eager_attention_forward, GemmaAttentionForward)
    try:
        assert torch.equal(_step_and_chunk(pi0, EAGER, torch.float32)["loss"], before)
    finally:
        pi05.set_attention(EAGER)


@pytest.mark.parametrize("name", sorted(BACKBONES))
def test_auto_takes_the_fused_path_where_a_backbone_has_one_and_a_path_it_lacks_is_refused(name: str) -> None:
    adapter = get_backbone(name)
    paths = adapter.spec.attentions
    assert paths and set(paths) <= {EAGER, FUSED} and len(set(paths)) == len(paths)
    assert adapter.resolve_attention("auto") == (FUSED if FUSED in paths else EAGER)
    for mode in {EAGER, FUSED} - set(paths):
        with pytest.raises(BackboneError, match=f"{name}: attention '{mode}' is not one of"):
            adapter.resolve_attention(mode)
