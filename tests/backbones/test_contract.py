"""The backbone contract: what every registered backbone (graftcache.backbone_registry.BACKBONES, the folders of
graftcache/backbones/) does the same way, one test each, parametrised over the registry, so a new backbone folder is
tested here without naming it anywhere. Where a case is about some backbones, its spec (BackboneSpec) selects them.

- a saved tiny loads back by folder and by hub id (HF cache), the same weights, processors and numbers;
- lean load = lerobot's own `from_pretrained` of the policy class, bit for bit;
- its native tower is the encoder `<name>-native`: measured spec, the policy's own tower and connector, the cache
  layout `extract` writes;
- graft and reset: the hash pinned at graft, every lerobot object given back, reset after training (plain and with
  LoRA) bit-identical to a fresh load with no copy of the weights kept;
- `loss` has the shape the spec's `loss_per_sample` says, and a fused pass of two cells equals each cell alone;
- activation checkpointing (spec `activation_checkpointing`) changes no gradient and never raises the peak.

Every control end to end through the CLI (train-tiny, extract of the native tower, fit with each control) is
tests/backbones/test_zoo_backbones_cli.py (its tiny policies are shared with tests/export/test_export.py). What is a
backbone's own (lerobot-equality of its loss and sampler, its graft slots, its released geometry) is its file
tests/backbones/test_<name>.py."""

from __future__ import annotations

import gc
import json
import sys
import types
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers.backbones import (
    ENC_DIM,
    TINY_SIZE,
    activation_checkpointing_peaks,
    fixed_noise_time,
    grafted,
    lowdim_stats,
    raw_features,
    raw_images,
    tiny,
)
from helpers.datasets import Written
from helpers.policies import assert_same_policy, checksum, kinds, lerobot_from_pretrained
from safetensors.torch import load_file, save_file

from devtools.released import hub_cache, publish
from graftcache.backbone_registry import BACKBONES, native_name
from graftcache.backbones import get_backbone, load_backbone
from graftcache.backbones.checkpoint import state_dict_sha256
from graftcache.backbones.lean_load import construct
from graftcache.backbones.patching import observe
from graftcache.backbones.tiny import TINY_MARKER, read_marker
from graftcache.backbones.tower_encoder import policy_pixels
from graftcache.encoders import get_spec, load_encoder
from graftcache.errors import BackboneError, EncoderError
from graftcache.extract import ExtractRequest, extract
from graftcache.graft import FusedProjector, GraftProjector
from graftcache.store import FeatureCache

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # tests/fixtures/torch_threads.py

NAMES = sorted(BACKBONES)


def _eval_loss(adapter, raw: dict) -> torch.Tensor:
    """The loss of `raw` under fixed draws, in eval mode (no dropout draws)."""
    adapter.policy.eval()
    noise, time = fixed_noise_time(adapter, len(raw["task"]))
    with torch.no_grad():
        return adapter.loss(adapter.prepare(dict(raw)), noise, time)


# ------------------------------------------------------------------------------------------------ loading
@pytest.mark.parametrize("name", NAMES)
def test_saved_tiny_loads_back_by_folder_and_by_hub_id(name: str, tmp_path: Path,
                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    """Saved as lerobot saves a policy (weights, config, both processors, graftcache's tiny marker), loaded offline
    from the folder and, placed in a hub cache snapshot, by `org/name`: the same weights, the same processors (their
    normalisation stats travelled with them) and the same loss."""
    original = tiny(name, seed=2)
    folder = original.save(tmp_path / "ckpt")
    assert {"config.json", "model.safetensors", "policy_preprocessor.json", "policy_postprocessor.json",
            TINY_MARKER} <= {p.name for p in folder.iterdir()}
    raw = raw_images(original, 2, size=TINY_SIZE)
    want = _eval_loss(original, raw)

    loaded = load_backbone(name, folder)
    assert type(loaded) is type(original)
    assert loaded.random_init and loaded.source == str(folder)  # a tiny checkpoint is never released weights
    assert loaded.policy_sha256 == original.policy_sha256 and loaded.n_params == original.n_params
    reference = original.policy.state_dict()
    assert all(torch.equal(reference[k], v) for k, v in loaded.policy.state_dict().items())
    torch.testing.assert_close(_eval_loss(loaded, raw), want, rtol=0, atol=0)

    cache, hub_id = tmp_path / "hub", f"graftcache-tests/{name}-tiny"
    with hub_cache(cache):
        monkeypatch.setenv("HF_HUB_CACHE", str(cache))
        publish(folder, hub_id, cache)
        from_hub = load_backbone(name, hub_id)
        assert type(original).read_token_grid(hub_id) == original.token_grid
        assert type(original).read_cameras(hub_id) == original.cameras
    assert from_hub.policy_sha256 == original.policy_sha256 and from_hub.random_init
    torch.testing.assert_close(_eval_loss(from_hub, raw), want, rtol=0, atol=0)


@pytest.mark.parametrize("name", NAMES)
def test_lean_load_equals_lerobots_from_pretrained_bit_for_bit(name: str, tmp_path: Path) -> None:
    """A policy built on the meta device and filled from its checkpoint (graftcache.backbones.lean_load) is what the
    policy class's own from_pretrained returns: every tensor, tie, flag and module class; nothing was randomly
    initialised on the way beyond what the constructor draws itself (no initialiser runs on the meta device)."""
    folder = tiny(name, seed=2).save(tmp_path / "ckpt")
    reference = lerobot_from_pretrained(name, folder)
    torch.manual_seed(0)
    adapter = get_backbone(name)
    config = adapter.saved_config(folder)
    construct(lambda: adapter._construct(config, read_marker(folder)), config)
    constructor_draws = torch.random.get_rng_state()  # what the constructor itself draws (GR00T: torch.randn)
    torch.manual_seed(0)
    lean = load_backbone(name, folder).policy
    assert torch.equal(torch.random.get_rng_state(), constructor_draws)  # loading draws nothing on top
    assert_same_policy(lean, reference)


@pytest.mark.parametrize("name", NAMES)
def test_a_checkpoint_missing_a_weight_is_an_error_not_a_random_model(name: str, tmp_path: Path) -> None:
    folder = tiny(name).save(tmp_path / "ckpt")
    weights = load_file(folder / "model.safetensors")
    key = max(weights)  # any weight the policy holds
    del weights[key]
    save_file(weights, folder / "model.safetensors")
    with pytest.raises(BackboneError, match=r"\(1 missing, 0 mis-shaped, 0 unexpected\): missing "):
        load_backbone(name, folder)


@pytest.mark.parametrize("name", NAMES)
def test_a_checkpoint_without_processors_needs_stats_and_normalises_with_them(name: str, tmp_path: Path) -> None:
    folder = tiny(name).save(tmp_path / "ckpt")
    for path in folder.glob("policy_*processor*"):
        path.unlink()
    with pytest.raises(BackboneError, match="no policy_preprocessor.json; pass dataset_stats"):
        load_backbone(name, folder)
    loaded = load_backbone(name, folder, dataset_stats=lowdim_stats())
    raw = raw_images(loaded, 2, size=TINY_SIZE)
    want = tiny(name).prepare(dict(raw))  # built with the same stats (QUANTILES or MEAN_STD, as the policy says)
    torch.testing.assert_close(loaded.prepare(dict(raw))["action"], want["action"])
    torch.testing.assert_close(loaded.prepare(dict(raw))["observation.state"], want["observation.state"])


# ------------------------------------------------------------------------------------------ native tower
@pytest.fixture(scope="module", params=NAMES)
def saved(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> tuple[str, Path]:
    """A tiny policy checkpoint folder as `--policy` names it."""
    folder = tmp_path_factory.mktemp(f"policy_{request.param}")
    tiny(request.param).save(folder)
    return request.param, folder


def test_native_towers_are_registered_under_the_backbone_names() -> None:
    for name in BACKBONES:
        spec = get_spec(native_name(name))
        assert spec.library == "native" and spec.name == f"{name}-native"


def test_native_encoder_outputs_equal_the_policy_tower_and_connector(saved: tuple[str, Path]) -> None:
    name, folder = saved
    encoder = load_encoder(native_name(name), policy=str(folder))
    adapter = tiny(name)  # the same seed-0 weights, loaded independently
    assert encoder.weights_info["sha256"] == adapter.policy_sha256
    assert encoder.weights_info["random_init"] is True  # a tiny checkpoint is never released weights
    frames = torch.from_numpy(np.random.default_rng(0).integers(0, 256, (2, 64, 80, 3), dtype=np.uint8))
    x = encoder.preprocess(frames)
    assert x.shape == (2, 3, encoder.spec.image_size, encoder.spec.image_size) and 0 <= x.min() and x.max() <= 1
    pixels = policy_pixels(frames, encoder.spec.image_size).float() / 255
    torch.testing.assert_close(x, pixels, rtol=0, atol=0)
    grid, extras = encoder.forward_with_extras(x)
    torch.testing.assert_close(grid, adapter.native_patch_grid(pixels))
    torch.testing.assert_close(extras["connector"], adapter.native_tokens(pixels))
    assert (*encoder.spec.grid, encoder.spec.width) == tuple(grid.shape[1:])
    assert encoder.extra_shapes["connector"] == tuple(extras["connector"].shape[1:])


def test_native_extract_stores_grid_and_connector_tokens(saved: tuple[str, Path], v3_video: Written,
                                                         tmp_path: Path) -> None:
    name, folder = saved
    result = extract(ExtractRequest(dataset=str(v3_video.root), encoder=native_name(name), grids=("unpooled", "2x2"),
                                    policy=str(folder), num_workers=0, batch_size=4, cache=str(tmp_path),
                                    progress=False), log=lambda _: None)
    cache = FeatureCache(result.path)
    assert cache.complete
    manifest = cache.manifest
    assert manifest.encoder_name == native_name(name) and manifest.random_init is True
    connector = list(load_encoder(native_name(name), policy=str(folder)).extra_shapes["connector"])
    assert manifest.extras["connector"] == connector
    assert cache.n_frames == sum(len(f) for (_, key), f in v3_video.frames.items() if key == v3_video.cameras[0])
    shapes = cache.layout["arrays"]  # per-frame shapes
    width = manifest.encoder["width"]
    assert sorted(p for p in shapes if p.endswith("/2x2")) == [f"features/{c}/2x2" for c in ("image", "image2")]
    assert all(shapes[p] == [4, width] for p in shapes if p.endswith("/2x2"))
    gh, gw = manifest.encoder["grid"]  # `unpooled`: the tower's own pre-connector grid, measured on the policy
    assert manifest.grids == [f"{gh}x{gw}", "2x2"] and manifest.unpooled_grid == f"{gh}x{gw}"
    assert [shapes[f"features/{c}/{gh}x{gw}"] for c in ("image", "image2")] == [[gh * gw, width]] * 2
    assert [shapes[p] for p in shapes if p.endswith("/connector")] == [connector, connector]
    json.dumps(manifest.to_dict())  # the manifest stays plain JSON


def test_native_encoder_needs_a_policy_and_refuses_other_weights(saved: tuple[str, Path]) -> None:
    name, folder = saved
    with pytest.raises(EncoderError, match="needs --policy"):
        load_encoder(native_name(name))
    with pytest.raises(EncoderError, match="takes its weights from --policy"):
        load_encoder(native_name(name), policy=str(folder), random_init=True)


# -------------------------------------------------------------------------------------------- graft, reset
@pytest.mark.parametrize("name", NAMES)
def test_policy_sha256_is_deterministic_and_pinned_at_graft(name: str) -> None:
    a, b, other = tiny(name), tiny(name), tiny(name, seed=1)
    assert a.policy_sha256 == b.policy_sha256 != other.policy_sha256
    before = b.policy_sha256
    b.graft(GraftProjector(ENC_DIM, b.lm_width))
    assert b.policy_sha256 == before


def lerobot_objects(policy: torch.nn.Module) -> dict[tuple[str, ...], object]:
    """Every lerobot module global, every attribute of a class lerobot defines, every method the policy's modules
    shadow on the instance, and every field of the policy's config, as the objects they are now (not the state a
    forward keeps for itself, such as Qwen's `rope_deltas`; the weights are compared by checksum)."""
    out: dict[tuple[str, ...], object] = {}
    for name, module in list(sys.modules.items()):
        if not name.startswith("lerobot"):
            continue
        for key, value in list(vars(module).items()):
            out["global", name, key] = value
            if isinstance(value, type) and value.__module__.startswith("lerobot"):
                for attribute, member in vars(value).items():
                    out["class", value.__module__, value.__qualname__, attribute] = member
    for path, module in policy.named_modules():
        for key, value in vars(module).items():
            if callable(getattr(type(module), key, None)) and not isinstance(value, torch.nn.Module):
                out["policy", path, key] = value
    for key, value in vars(policy.config).items():
        out["config", key] = value
    return out


@pytest.mark.parametrize("name", NAMES)
def test_reset_gives_back_every_lerobot_object_and_the_loaded_weights(name: str) -> None:
    """Every change an adapter makes to lerobot goes through one recorded mechanism (graftcache.backbones.patching):
    after load -> graft -> fit steps (and checkpointed ones where the spec allows) -> reset, each lerobot module
    global, class attribute and policy attribute is the original object again, and the weights are a fresh load's."""
    adapter = tiny(name)
    before = lerobot_objects(adapter.policy)
    with observe() as changes:
        torch.manual_seed(0)
        adapter.graft(GraftProjector(ENC_DIM, adapter.lm_width))
        optimiser = torch.optim.AdamW(adapter.projector.parameters(), lr=1e-3)
        adapter.policy.train()
        for step in range(2):
            batch = adapter.prepare(raw_features(adapter, 2, seed=step))
            adapter.loss(batch).mean().backward()
            optimiser.step()
            optimiser.zero_grad()
        adapter.predict(batch)
        if adapter.spec.can_recompute:
            adapter.set_recompute(True)
            adapter.loss(batch).mean().backward()
            adapter.set_recompute(False)
        for mode in (*adapter.spec.attentions[1:], adapter.spec.attentions[0]):  # the other path, then back
            adapter.set_attention(mode)
            adapter.loss(batch).mean().backward()
        adapter.reset()
    assert changes, "a graft changes the policy (its image method at least), through graftcache.backbones.patching"
    assert [(c.owner, c.attribute) for c in changes if not c.is_restored()] == []
    after = lerobot_objects(adapter.policy)
    changed = sorted(k for k, v in before.items() if k in after and after[k] is not v)
    added = sorted(k for k in after if k not in before and k[0] in ("policy", "config"))
    assert changed == [] and added == []
    assert [k for k in after if k[0] == "policy"] == [], "a method shadowed on the policy outlives reset"
    assert state_dict_sha256(adapter.policy) == state_dict_sha256(tiny(name).policy)


def _steps(adapter, steps: int = 3) -> None:
    """Training steps as the fit loop takes them (AdamW on every trainable parameter, with weight decay)."""
    params = [p for p in adapter.policy.parameters() if p.requires_grad]
    optimizer = torch.optim.AdamW(params, lr=1e-2, weight_decay=0.1)
    adapter.policy.train()
    for step in range(steps):
        batch = adapter.prepare(raw_features(adapter, 2, seed=step))
        noise, time = fixed_noise_time(adapter, 2, seed=step)
        loss = adapter.loss(batch, noise=noise, time=time).mean()
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()


def _reachable_tensor_bytes(root: object) -> int:
    """Bytes of the distinct storages of every tensor reachable from `root` through attributes and containers
    (not through functions, classes or modules: those lead to global state)."""
    skip = (types.ModuleType, types.FunctionType, types.BuiltinFunctionType, type)
    seen, storages, todo = set(), {}, [root]
    while todo:
        obj = todo.pop()
        if id(obj) in seen or isinstance(obj, skip):
            continue
        seen.add(id(obj))
        if isinstance(obj, torch.Tensor):
            storage = obj.untyped_storage()
            storages[storage.data_ptr()] = storage.nbytes()
            if obj.grad is not None:
                todo.append(obj.grad)
            continue
        todo.extend(gc.get_referents(obj))
    return sum(storages.values())


@pytest.mark.parametrize("lora", [False, True], ids=["graft", "lora"])
@pytest.mark.parametrize("name", NAMES)
def test_reset_after_training_is_bit_identical_to_a_fresh_load_and_keeps_no_copy(name: str, lora: bool,
                                                                                   tmp_path: Path) -> None:
    """Two cells on one backbone, as LoadedBackbones hands it out (graft, LoRA on the language model, fit steps, reset):
    after each, the policy is a fresh load's bit for bit, its modules and requires_grad flags are back, and
    nothing the size of the model was held beside it."""
    folder = tiny(name, seed=1).save(tmp_path / "ckpt")
    fresh = checksum(load_backbone(name, folder).policy)
    adapter = load_backbone(name, folder)
    model_bytes = _reachable_tensor_bytes(adapter.policy)
    adapter.prepare(raw_images(adapter, 2, size=TINY_SIZE))  # processors build what they keep on first use
    loaded_bytes = _reachable_tensor_bytes(adapter)  # the policy, its processors and stats, before any cell
    modules = kinds(adapter.policy)
    grads = {n: p.requires_grad for n, p in adapter.policy.named_parameters()}
    for _ in range(2):
        adapter.graft(GraftProjector(ENC_DIM, adapter.lm_width))
        if lora:
            adapter.add_lora(rank=2)
            lm = adapter._module_groups()["language model"]
            in_lm = {id(p) for m in (lm if isinstance(lm, tuple) else (lm,)) for p in m.parameters()}
            adapted = [p for n, p in adapter.policy.named_parameters() if "lora_" in n]
            assert adapted and all(id(p) in in_lm for p in adapted)  # LoRA adapts the language model only
        _steps(adapter)
        grafted_extra = _reachable_tensor_bytes(adapter) - loaded_bytes
        adapter.reset()
        # nothing the size of the model is held beside it: the projector's (and LoRA's) tensors, tokens, stats
        assert grafted_extra < 0.5 * model_bytes, (grafted_extra, model_bytes)
        assert not adapter.grafted and adapter.projector is None
        assert kinds(adapter.policy) == modules  # LoRA layers removed
        assert {n: p.requires_grad for n, p in adapter.policy.named_parameters()} == grads
        lm = adapter._module_groups()["language model"]
        assert not any(hasattr(m, "peft_config") for m in (lm if isinstance(lm, tuple) else (lm,)))
        assert checksum(adapter.policy) == fresh


# ----------------------------------------------------------------------------------------- loss, passes
@pytest.mark.parametrize("name", NAMES)
def test_loss_has_the_shape_the_spec_says(name: str) -> None:
    """The flag that lets a backbone's cells share a pass (`loss_per_sample`, read by graftcache.fit.plan.Plan.pass_key)
    matches its loss: one value a sample, or one mean over the batch."""
    adapter = grafted(name)
    with torch.no_grad():
        loss = adapter.loss(adapter.prepare(raw_features(adapter, 3)), *fixed_noise_time(adapter, 3))
    assert loss.shape == ((3,) if adapter.spec.loss_per_sample else ())


@pytest.mark.parametrize("name", NAMES)
def test_a_fused_pass_equals_each_projector_alone(name: str) -> None:
    """One backbone pass of several cells (`fit --cells-per-pass`, graftcache.graft.FusedProjector): two projectors
    fused over a batch of two samples give each sample the loss its own projector gives it alone, or the backbone is
    kept out of fused passes (spec `loss_per_sample` False)."""
    adapter = tiny(name)
    if not adapter.spec.loss_per_sample:  # graftcache.fit.plan.Plan.pass_key runs its cells alone
        pytest.skip(f"{name}: one loss a batch, cells never share a pass")
    adapter.policy.eval()  # no dropout (tiny X-VLA's): its draws for a batch of two are not those for one sample
    torch.manual_seed(0)
    members = [GraftProjector(ENC_DIM, adapter.lm_width) for _ in range(2)]
    raw = raw_features(adapter, 2)
    noise, time = fixed_noise_time(adapter, 2)
    alone = []
    for i, projector in enumerate(members):
        adapter.graft(projector)
        one = {k: v[i:i + 1] for k, v in raw.items()}
        with torch.no_grad():
            alone.append(adapter.loss(adapter.prepare(one), noise[i:i + 1], time[i:i + 1]))
        adapter.reset()
    fused = FusedProjector(members)
    adapter.graft(fused)
    with torch.no_grad(), fused.rows([1, 1]):
        together = adapter.loss(adapter.prepare(raw), noise, time)
    torch.testing.assert_close(together, torch.cat(alone))


# ------------------------------------------------------------------------------- activation checkpointing
@pytest.mark.parametrize("name", NAMES)
def test_activation_checkpointing_keeps_the_gradients_and_never_raises_the_peak(name: str) -> None:
    """The frozen LM and expert recompute activations in backward (graftcache/backbones/activation_checkpointing.py):
    the projector's gradients do not change, switching off restores the plain step, and a checkpointed step holds no
    more memory (measured as tensors alive at once). How much lower is each backbone's own (its file: the tiny
    step's peak may be set before its LM runs, as in VLA-JEPA and Wall-X)."""
    adapter = grafted(name)
    if not adapter.spec.can_recompute:
        pytest.skip(f"{name}: no activation checkpointing (spec)")
    plain, checkpointed = activation_checkpointing_peaks(adapter)
    assert checkpointed <= plain, (checkpointed, plain)
