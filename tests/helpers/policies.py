"""Comparing two lerobot policies bit for bit (lean load against lerobot's own from_pretrained, a reset backbone
against a fresh load), and lerobot's own from_pretrained of any registered backbone's checkpoint."""

from __future__ import annotations

import hashlib
from pathlib import Path

import torch
from torch import nn

from graftcache.backbones import get_backbone
from graftcache.backbones.tiny import read_marker


def lerobot_from_pretrained(name: str, folder: Path) -> nn.Module:
    """The slow path, for any registered backbone: the policy class's own `from_pretrained` (random init in fp32 on
    the device, the checkpoint read and copied over, its own key renames and casts), with the one difference that
    the instance it fills is constructed as the adapter constructs it (`_construct`: a tiny checkpoint's sizes, local
    tokenizers), here for real rather than on the meta device."""
    adapter = get_backbone(name)
    config = adapter._read_config(folder)
    config.device = "cpu"
    marker = read_marker(folder)
    adapter._configure(folder, config, marker)
    from lerobot.policies.factory import get_policy_class

    class Reference(get_policy_class(config.type)):
        def __new__(cls, config, **kwargs):  # what lerobot's from_pretrained instantiates: cls(config, **kwargs)
            return adapter._construct(config, marker)

    return Reference.from_pretrained(folder, config=config, strict=True)


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


def assert_same_policy(lean: nn.Module, reference: nn.Module) -> None:
    """Every tensor (dtype, shape, device, bytes), tie, requires_grad flag and module class of `lean` is
    `reference`'s, and no tensor of `lean` is left on the meta device."""
    want, got = tensors(reference), tensors(lean)
    assert got.keys() == want.keys()
    assert not [n for n, t in got.items() if t.is_meta]  # non-persistent buffers (rotary inv_freq) included
    for n, t in want.items():
        assert (got[n].dtype, got[n].shape, got[n].device) == (t.dtype, t.shape, t.device), n
        assert torch.equal(bits(got[n]), bits(t)), n
    assert ties(lean) == ties(reference)
    assert {n: p.requires_grad for n, p in lean.named_parameters()} == {
        n: p.requires_grad for n, p in reference.named_parameters()}
    assert kinds(lean) == kinds(reference)
