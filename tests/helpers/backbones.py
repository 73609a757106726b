"""Shared helpers for the backbone and graft tests: tiny adapters, stats and raw batches."""

from __future__ import annotations

from collections.abc import Callable

import pytest
import torch

from graftcache.backbones import BACKBONES, get_backbone, load_backbone
from graftcache.backbones.base import BackboneAdapter
from graftcache.backbones.spec import BackboneSpec
from graftcache.backbones.tiny import TinyBuild
from graftcache.errors import BackboneError
from graftcache.fit.controls import PassThroughProjector
from graftcache.graft import GraftProjector, feature_key
from helpers.memory import peak_tensor_bytes

TINY = TinyBuild()
ENC_DIM = 48
#: The tiny zoo policies' frames (train-tiny's size): each processor makes a 4x4 token grid of them.
TINY_SIZE = 128
TASKS = (
    "pick up the black bowl between the plate and the ramekin and place it on the plate",
    "open the middle drawer of the cabinet",
    "put the bowl on the stove",
)


def backbones_where(predicate: Callable[[BackboneSpec], bool]) -> list[str]:
    """The registered backbones whose spec satisfies `predicate`, sorted (for tests about some backbones: they are
    selected by what their spec declares, never by name; imports the adapters, hence lerobot)."""
    return [name for name in sorted(BACKBONES) if predicate(get_backbone(name).spec)]


def lowdim_stats(state_dim: int = TINY.state_dim, action_dim: int = TINY.action_dim) -> dict:
    """lerobot-format stats with every field the SmolVLA (MEAN_STD) and pi0.5 (QUANTILES) processors read."""
    def fields(n: int, scale: float) -> dict[str, torch.Tensor]:
        return {
            "mean": torch.full((n,), 0.1), "std": torch.full((n,), scale),
            "min": torch.full((n,), -2 * scale), "max": torch.full((n,), 2 * scale),
            "q01": torch.full((n,), -1.5 * scale), "q99": torch.full((n,), 1.5 * scale),
        }

    return {"observation.state": fields(state_dim, 0.5), "action": fields(action_dim, 0.8)}


def tiny(name: str, seed: int = 0) -> BackboneAdapter:
    return load_backbone(name, "tiny", dataset_stats=lowdim_stats(), tiny=TinyBuild(seed=seed))


def grafted(name: str, enc_dim: int = ENC_DIM, seed: int = 0) -> BackboneAdapter:
    adapter = tiny(name, seed)
    torch.manual_seed(seed)
    adapter.graft(GraftProjector(enc_dim, adapter.lm_width))
    return adapter


def raw_lowdim(adapter: BackboneAdapter, batch: int, seed: int = 0) -> dict:
    """Raw (unnormalised) state, action chunk, padding flags and task strings."""
    g = torch.Generator().manual_seed(seed)
    pad = torch.zeros(batch, adapter.chunk_size, dtype=torch.bool)
    pad[0, -3:] = True  # the first sample ran off the end of its episode
    return {
        "observation.state": torch.randn(batch, adapter.state_dim, generator=g) * 0.5,
        "action": torch.randn(batch, adapter.chunk_size, adapter.action_dim, generator=g) * 0.8,
        "action_is_pad": pad,
        "task": [TASKS[i % len(TASKS)] for i in range(batch)],
    }


def raw_features(adapter: BackboneAdapter, batch: int, enc_dim: int = ENC_DIM, seed: int = 0) -> dict:
    """A raw batch with cached features [B, T, enc_dim] per camera at the backbone's token grid."""
    g = torch.Generator().manual_seed(seed + 1)
    tokens = adapter.token_grid[0] * adapter.token_grid[1]
    feats = {feature_key(c): torch.randn(batch, tokens, enc_dim, generator=g) for c in adapter.cameras}
    return {**feats, **raw_lowdim(adapter, batch, seed)}


def raw_images(adapter: BackboneAdapter, batch: int, seed: int = 0, size: int = 96) -> dict:
    """A raw batch with pixels [B, 3, H, W] in [0, 1] per camera (the native, ungrafted policy)."""
    g = torch.Generator().manual_seed(seed + 2)
    images = {k: torch.rand(batch, 3, size, size, generator=g) for k in adapter.camera_keys}
    return {**images, **raw_lowdim(adapter, batch, seed)}


def fixed_noise_time(adapter: BackboneAdapter, batch: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed + 3)
    return adapter.sample_noise(batch, g), torch.rand(batch, generator=g) * 0.9 + 0.05


def assert_native_control_reproduces(native: BackboneAdapter, control: BackboneAdapter, batch: int,
                                     size: int = 96) -> None:
    """Cached post-connector tokens of `native` through `control`'s pass-through projector give the loss and the
    predicted chunk `native` gives on pixels (`native` and `control`: two loads of one policy)."""
    raw = raw_images(native, batch, size=size)
    noise, time = fixed_noise_time(native, batch)
    tokens = {feature_key(k): native.native_tokens(raw[k]) for k in native.camera_keys}
    with torch.no_grad():
        pixel_loss = native.loss(native.prepare(raw), noise, time)
        pixel_chunk = native.predict(native.prepare(raw), noise)
    control.graft(PassThroughProjector(control.lm_width))
    assert control.freeze_report().trainable == 0
    cached = {**{k: v for k, v in raw.items() if not k.startswith("observation.images.")}, **tokens}
    with torch.no_grad():
        torch.testing.assert_close(control.loss(control.prepare(cached), noise, time), pixel_loss)
        torch.testing.assert_close(control.predict(control.prepare(cached), noise), pixel_chunk)


def assert_tiny_zoo_geometry(adapter: BackboneAdapter, max_action_dim: int, connector: int,
                             params: int) -> dict[str, int]:
    """What every tiny zoo policy (EO-1, GR00T, Wall-X, VLA-JEPA, EVO1) shares: a 4x4 token grid of 64-wide tokens
    from an 8x8 grid of 32-wide patches, two cameras, 10-step chunks, its parameter count (`params`) in the
    freeze report, and a `connector` of the given size. Returns the report's {module: parameters}."""
    assert adapter.token_grid == (4, 4) and adapter.lm_width == 64 and adapter.embed_scale == 1.0
    assert adapter.cameras == ("image", "image2") and adapter.max_action_dim == max_action_dim
    assert adapter.chunk_size == 10
    images = torch.rand(2, 3, TINY_SIZE, TINY_SIZE)
    assert adapter.native_patch_grid(images).shape == (2, 8, 8, 32)
    assert adapter.native_tokens(images).shape == (2, 16, 64)
    assert adapter.n_params == params
    report = {r.module: r.params for r in adapter.freeze_report().rows}
    assert sum(report.values()) == params and report["connector"] == connector
    return report


def assert_refuses_odd_token_counts(adapter: BackboneAdapter, raw: dict, noise: torch.Tensor,
                                    time: torch.Tensor, slots: bool = False) -> None:
    """A grafted pad-filling adapter (tiny, 4x4 token grid) refuses, in one line, 6 cached tokens per camera (neither
    its grid nor a square one) and cameras carrying different token counts; with `slots`, also a prepared batch
    whose features no longer match its prompt's 16 image slots per camera."""
    odd = {**raw, **{feature_key(k): raw[feature_key(k)][:, :6] for k in adapter.camera_keys}}
    with pytest.raises(BackboneError, match="6 cached tokens per camera is neither the token grid 4x4 nor a square"):
        adapter.loss(adapter.prepare(odd), noise, time)
    uneven = {**raw, feature_key("image"): raw[feature_key("image")][:, :9]}
    with pytest.raises(BackboneError, match="different token counts"):
        adapter.loss(adapter.prepare(uneven), noise, time)
    if slots:
        batch = adapter.prepare(raw)
        batch[feature_key("image2")] = batch[feature_key("image2")][:, :4]
        with pytest.raises(BackboneError, match=r"features have \[4, 16\] tokens per camera; the prompt has \[16\]"):
            adapter.loss(batch, noise, time)


def pooled_raw(adapter: BackboneAdapter, batch: int = 2) -> dict:
    """A raw batch whose cached features are a pool-2x2 control's: 4 tokens per camera."""
    pooled = {feature_key(k): torch.randn(batch, 4, ENC_DIM) for k in adapter.camera_keys}
    return {**raw_features(adapter, batch), **pooled}


def lm_inputs_of_loss(adapter: BackboneAdapter, lm: torch.nn.Module, batch: dict, noise: torch.Tensor,
                      time: torch.Tensor) -> tuple[dict, torch.Tensor]:
    """The keyword inputs `lm` (the policy's language model) is called with during `adapter.loss`, and the loss."""
    seen: dict = {}
    hook = lm.register_forward_pre_hook(lambda m, args, kwargs: seen.update(kwargs), with_kwargs=True)
    try:
        loss = adapter.loss(batch, noise, time)
    finally:
        hook.remove()
    return seen, loss


def projected_cameras(adapter: BackboneAdapter, raw: dict) -> torch.Tensor:
    """What a grafted adapter must write into its image slots, independently computed: every sample's cached features
    camera after camera, through the projector."""
    cameras = [raw[feature_key(k)] for k in adapter.camera_keys]
    return adapter.projector(torch.stack(cameras, dim=1).flatten(0, 2))


def assert_projector_trained(adapter: BackboneAdapter, loss: torch.Tensor) -> None:
    """The loss back-propagates into every projector parameter (a nonzero gradient each)."""
    loss.mean().backward()
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in adapter.projector.parameters())


def activation_checkpointing_peaks(adapter: BackboneAdapter, batch: int = 8) -> tuple[int, int]:
    """(plain, checkpointed) peak tensor bytes of one training step of a grafted adapter, after checking that
    activation checkpointing changes no gradient and that switching it off again restores the plain step."""
    adapter.policy.train()
    prepared = adapter.prepare(raw_features(adapter, batch))
    noise, time = fixed_noise_time(adapter, batch)
    params = [p for p in adapter.policy.parameters() if p.requires_grad]

    def step() -> None:
        torch.manual_seed(0)  # X-VLA trains with dropout: every step draws the same masks
        adapter.loss(prepared, noise=noise, time=time).mean().backward()

    grads, peaks = {}, {}
    for on in (False, True, False):  # off again: the switch restores the plain step
        adapter.set_recompute(on)
        assert adapter.recomputing is on
        for p in params:
            p.grad = None
        peaks.setdefault(on, []).append(peak_tensor_bytes(step))
        grads.setdefault(on, []).append([p.grad.clone() for p in params])
    assert params and all(g is not None for g in grads[True][0])
    for plain, checkpointed in zip(grads[False][0], grads[True][0], strict=True):
        torch.testing.assert_close(checkpointed, plain, rtol=0, atol=1e-6)
    assert peaks[False][1] == pytest.approx(peaks[False][0], rel=0.03)  # pi0-FAST's second plain step: +2%
    return peaks[False][0], peaks[True][0]
