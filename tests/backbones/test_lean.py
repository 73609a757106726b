"""Lean loading and the undo of a graft: a policy built on the meta device and filled from its checkpoint equals
lerobot's own from_pretrained bit for bit, and a reset backbone equals a fresh load bit for bit, with no copy of
its weights kept anywhere."""

from __future__ import annotations

import gc
import hashlib
import json
import re
import types
from pathlib import Path

import pytest
import torch
from helpers.backbones import ENC_DIM, fixed_noise_time, raw_features, tiny
from torch import nn

from graftcache.backbones import get_backbone, load_backbone
from graftcache.backbones.lean import read_into
from graftcache.backbones.paligemma import pi05_tiny_sizes
from graftcache.backbones.tiny import read_marker
from graftcache.backbones.tiny_assets import SMOLVLM_DIR
from graftcache.errors import BackboneError
from graftcache.graft import GraftProjector

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # tests/fixtures/torch_threads.py

NAMES = ("smolvla", "pi05")


def lerobot_from_pretrained(name: str, folder: Path) -> nn.Module:
    """The slow path: lerobot's own from_pretrained, as graftcache loaded policies before (random init in
    fp32, then the checkpoint copied over)."""
    config = get_backbone(name)._read_config(folder)
    config.device = "cpu"
    if name == "smolvla":
        from lerobot.policies.smolvla.modeling_smolvla import SmolVLAPolicy

        config.load_vlm_weights, config.vlm_model_name = False, str(SMOLVLM_DIR)
        return SmolVLAPolicy.from_pretrained(folder, config=config)
    from lerobot.policies.pi05.modeling_pi05 import PI05Policy

    with pi05_tiny_sizes(read_marker(folder)["geometry"]):
        return PI05Policy.from_pretrained(folder, config=config, strict=True)


def bits(t: torch.Tensor) -> torch.Tensor:
    """A tensor's raw bytes (so -0.0 != 0.0 and NaN payloads count)."""
    return t.detach().contiguous().reshape(-1).view(torch.uint8)


def tensors(policy: nn.Module) -> dict[str, torch.Tensor]:
    """Every parameter and buffer, persistent or not, by name (tied names each listed)."""
    return {**dict(policy.named_parameters(remove_duplicate=False)),
            **dict(policy.named_buffers(remove_duplicate=False))}


def checksum(policy: nn.Module) -> str:
    """sha256 over name, dtype, shape, device and bytes of every parameter and buffer."""
    h = hashlib.sha256()
    for name, t in sorted(tensors(policy).items()):
        h.update(f"{name}|{t.dtype}|{tuple(t.shape)}|{t.device}|".encode())
        h.update(bits(t).numpy().tobytes())
    return h.hexdigest()


def kinds(policy: nn.Module) -> dict[str, str]:
    """Module name -> class name (pi0.5's Gemma layers are classes made per construction)."""
    return {n: type(m).__qualname__ for n, m in policy.named_modules()}


def ties(policy: nn.Module) -> list[list[str]]:
    groups: dict[int, list[str]] = {}
    for name, t in tensors(policy).items():
        groups.setdefault(id(t), []).append(name)
    return sorted(sorted(g) for g in groups.values())


@pytest.mark.parametrize(("name", "dtype"), [("smolvla", None), ("pi05", None), ("pi05", "bfloat16")])
def test_lean_load_equals_lerobots_from_pretrained_bit_for_bit(name: str, dtype: str | None, tmp_path: Path) -> None:
    """fp32 tiny checkpoints; pi0.5 also with its config asking for bf16 (LM cast, vision path and norms fp32):
    each tensor is cast on the way in, as load_state_dict's copy casts."""
    folder = tiny(name, seed=2).save(tmp_path / "ckpt")
    if dtype is not None:
        config = json.loads((folder / "config.json").read_text())
        (folder / "config.json").write_text(json.dumps({**config, "dtype": dtype}))
    reference = lerobot_from_pretrained(name, folder)
    rng = torch.random.get_rng_state()
    lean = load_backbone(name, folder).policy
    assert torch.equal(torch.random.get_rng_state(), rng)  # nothing was randomly initialised

    want, got = tensors(reference), tensors(lean)
    assert got.keys() == want.keys()
    assert not [n for n, t in got.items() if t.is_meta]  # non-persistent buffers (rotary inv_freq) included
    for n, t in want.items():
        assert (got[n].dtype, got[n].shape, got[n].device) == (t.dtype, t.shape, t.device), n
        assert torch.equal(bits(got[n]), bits(t)), n
    assert dtype is None or {t.dtype for t in got.values()} >= {torch.bfloat16, torch.float32}
    assert ties(lean) == ties(reference)
    assert {n: p.requires_grad for n, p in lean.named_parameters()} == {
        n: p.requires_grad for n, p in reference.named_parameters()}
    assert kinds(lean) == kinds(reference)


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


@pytest.mark.parametrize(("name", "lora"), [("smolvla", False), ("smolvla", True), ("pi05", False), ("pi05", True)])
def test_reset_after_training_is_bit_identical_to_a_fresh_load_and_keeps_no_copy(name: str, lora: bool,
                                                                                   tmp_path: Path) -> None:
    folder = tiny(name, seed=1).save(tmp_path / "ckpt")
    fresh = checksum(load_backbone(name, folder).policy)
    adapter = load_backbone(name, folder)
    model_bytes = _reachable_tensor_bytes(adapter.policy)
    modules = kinds(adapter.policy)
    grads = {n: p.requires_grad for n, p in adapter.policy.named_parameters()}
    for _ in range(2):  # a second cell on the same backbone, as the pool hands it out
        adapter.graft(GraftProjector(ENC_DIM, adapter.lm_width))
        if lora:
            adapter.add_lora(rank=2)
        _steps(adapter)
        grafted_extra = _reachable_tensor_bytes(adapter) - model_bytes
        projector = sum(p.numel() * p.element_size() * 4 for p in adapter.projector.parameters())  # +grad, 2 moments
        adapter.reset()
        # nothing the size of the model is held beside it: the projector's (and LoRA's) tensors, tokens, stats
        assert grafted_extra < 0.5 * model_bytes, (grafted_extra, model_bytes, projector)
        assert not adapter.grafted and adapter.projector is None
        assert kinds(adapter.policy) == modules  # LoRA layers removed
        assert {n: p.requires_grad for n, p in adapter.policy.named_parameters()} == grads
        assert not hasattr(adapter._module_groups()["language model"], "peft_config")
        assert checksum(adapter.policy) == fresh


def test_a_frozen_weight_written_while_grafted_is_an_error_at_reset() -> None:
    adapter = tiny("smolvla")
    adapter.graft(GraftProjector(ENC_DIM, adapter.lm_width))
    with torch.no_grad():
        adapter.policy.model.state_proj.weight.add_(1.0)
    with pytest.raises(BackboneError, match=r"1 frozen policy tensors were written.*state_proj\.weight.*reload"):
        adapter.reset()
