"""Graft surgery on a backbone: tower -> pass-through, connector -> projector, freezing, LoRA, undo.

The backbone's vision tower is replaced by `PassThroughTower` (so lerobot's own `embed_image` runs
unchanged and simply receives cached features) and its connector by the projector; everything but the
projector is frozen. A `Graft` records all of it and `reset` undoes it, so one loaded policy serves every cell
of one command, without a copy of its weights.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import Any

import torch
from torch import nn
from transformers.modeling_outputs import BaseModelOutput

from graftcache.backbones.patching import Patches
from graftcache.errors import BackboneError
from graftcache.graft import feature_key

#: Projections of a Llama / Gemma decoder layer that the `lora` control adapts (attention and MLP).
LORA_TARGETS = ("q_proj", "k_proj", "v_proj", "o_proj", "gate_proj", "up_proj", "down_proj")


class PassThroughTower(nn.Module):
    """Stands in for a Hugging Face vision tower: returns its input as `.last_hidden_state`.

    `.dtype` exists because SmolVLA's `embed_image` casts its input to `vision_model.dtype`.
    """

    def __init__(self) -> None:
        super().__init__()
        self.register_buffer("_dtype_anchor", torch.zeros(0), persistent=False)

    @property
    def dtype(self) -> torch.dtype:
        return self._dtype_anchor.dtype

    def forward(self, pixel_values: torch.Tensor, **_: object) -> BaseModelOutput:
        return BaseModelOutput(last_hidden_state=pixel_values)


def freeze_all_but(model: nn.Module, trainable: nn.Module) -> None:
    """Freeze every parameter of `model`, then unfreeze those of `trainable` (which may be outside it)."""
    for p in model.parameters():
        p.requires_grad_(False)
    for p in trainable.parameters():
        p.requires_grad_(True)


@dataclass(frozen=True)
class FreezeRow:
    module: str
    params: int
    trainable: int


@dataclass(frozen=True)
class FreezeReport:
    """Which modules are frozen or trainable, with parameter counts (logged by the fit loop)."""

    rows: tuple[FreezeRow, ...]

    @property
    def total(self) -> int:
        return sum(r.params for r in self.rows)

    @property
    def trainable(self) -> int:
        return sum(r.trainable for r in self.rows)

    def __str__(self) -> str:
        width = max(len(r.module) for r in self.rows)
        lines = [f"{'module':<{width}}  {'params':>13}  {'trainable':>13}  state"]
        for r in self.rows:
            state = "trainable" if r.trainable == r.params and r.params else "frozen" if not r.trainable else "partial"
            lines.append(f"{r.module:<{width}}  {r.params:>13,}  {r.trainable:>13,}  {state}")
        lines.append(f"{'total':<{width}}  {self.total:>13,}  {self.trainable:>13,}")
        return "\n".join(lines)

    def changes(self, base: FreezeReport) -> str:
        """What differs from `base` (another graft of the same policy), row by row and the total, on one line: a
        log says the whole report once per loaded policy and then only this (e.g. LoRA's trainable share of the
        language model, a wider encoder's projector)."""
        before = {r.module: r for r in base.rows}
        rows = [r for r in self.rows if before.get(r.module) != r]
        return "; ".join([*(f"{r.module} {r.params:,} params, {r.trainable:,} trainable" for r in rows),
                          f"total {self.total:,} params, {self.trainable:,} trainable"])


def freeze_report(groups: Mapping[str, nn.Module | tuple[nn.Module, ...]], model: nn.Module) -> FreezeReport:
    """Count parameters per named group; each parameter is counted once (tied weights included),
    and anything not covered by a group is reported as "other" so the totals match `model`."""
    seen: set[int] = set()
    rows = []

    def count(params: Iterable[nn.Parameter]) -> tuple[int, int]:
        total = trainable = 0
        for p in params:
            if id(p) in seen:
                continue
            seen.add(id(p))
            total += p.numel()
            trainable += p.numel() if p.requires_grad else 0
        return total, trainable

    for name, modules in groups.items():
        modules = modules if isinstance(modules, tuple) else (modules,)
        total, trainable = count(p for m in modules for p in m.parameters())
        rows.append(FreezeRow(name, total, trainable))
    total, trainable = count(model.parameters())
    if total:
        rows.append(FreezeRow("other", total, trainable))
    return FreezeReport(tuple(rows))


class Graft:
    """One graft on a policy and everything needed to take it off again, held by the graft itself as peft's
    tuner holds its base model: its changes to the policy (the modules it replaced, the methods it shadowed, as one
    graftcache.backbones.patching.Patches record), the requires_grad flags it changed, and the LoRA tuner. `undo()`
    gives the policy back as it was loaded. Nothing is copied for that: a graft writes no frozen weight (projector
    and LoRA modules are its own, and LoRA is unloaded, never merged), which `undo()` checks on every tensor's
    version counter."""

    def __init__(self, policy: nn.Module, projector: nn.Module) -> None:
        self.policy = policy
        self.projector = projector
        self.patches = Patches()  # every attribute the graft set on the policy's modules, with what it replaced
        self._requires_grad = {n: p.requires_grad for n, p in policy.named_parameters()}
        self._versions = {n: t._version for n, t in policy.state_dict(keep_vars=True).items()}
        self._lora = None  # peft's LoraModel around the adapted module: its unload() removes the adapters

    def replace(self, owner: nn.Module, attribute: str, module: nn.Module) -> None:
        """setattr that remembers the module it replaced."""
        self.patches.set(owner, attribute, module)

    def override(self, method: str, replacement: Callable) -> None:
        """Shadow one of the policy's methods with `replacement` (an instance attribute) until undone."""
        self.patches.set(self.policy, method, replacement)

    def shadow(self, module: nn.Module, name: str, replacement: Callable) -> None:
        """Shadow `module.name` with `replacement(own, module, ...)` until undone (graftcache.backbones.patching)."""
        self.patches.shadow(module, name, replacement)

    def add_lora(self, module: nn.Module, config) -> None:
        """peft LoRA adapters injected into `module` in place; only they become trainable in it."""
        from peft import LoraModel

        self._lora = LoraModel(module, config, "default")
        for name, param in module.named_parameters():
            param.requires_grad_("lora_" in name)

    def undo(self) -> None:
        """Remove LoRA (unloaded without merging), undo the changes (the replaced modules back, the shadows gone),
        restore the requires_grad flags; BackboneError if a frozen tensor was written meanwhile (the policy is then
        not the one loaded: reload it)."""
        if self._lora is not None:
            self._lora.unload()  # each LoRA layer -> its base layer; peft_config dropped from the module
            self._lora = None
        self.patches.undo()
        for name, param in self.policy.named_parameters():
            param.requires_grad_(self._requires_grad.get(name, param.requires_grad))
        written = [n for n, t in self.policy.state_dict(keep_vars=True).items()
                   if t._version != self._versions.get(n, t._version)]
        if written:
            raise BackboneError(f"{len(written)} frozen policy tensors were written while grafted (e.g. "
                                f"{written[0]}); the policy is no longer the one loaded: reload it")


class GraftSurgery:
    """The surgery half of a BackboneAdapter (mixed into it; uses its policy, device and slots): it makes and
    holds the current `Graft`."""

    _graft: Graft | None = None

    @property
    def grafted(self) -> bool:
        return self._graft is not None

    @property
    def projector(self) -> nn.Module | None:
        """The grafted projector (None when not grafted)."""
        return None if self._graft is None else self._graft.projector

    def graft(self, projector: nn.Module) -> None:
        """Replace tower and connector, read images from cached features, freeze all but `projector`."""
        if self.grafted:
            raise BackboneError(f"{self.name}: already grafted")
        width = getattr(projector, "out_features", None)
        if width != self.lm_width:
            raise BackboneError(f"{self.name}: projector outputs width {width}, the LM expects {self.lm_width}")
        _ = self.policy_sha256  # pin the hash of the loaded weights before the surgery changes the modules
        _ = self.n_params  # and their count (results column backbone_params)
        graft = Graft(self.policy, projector.to(self.device))
        owner, tower, connector = self._vision_slots()
        graft.replace(owner, tower, PassThroughTower().to(self.device))
        graft.replace(owner, connector, graft.projector)
        graft.override(self.image_method, self._feature_images)
        self._patch_graft(graft)
        freeze_all_but(self.policy, graft.projector)
        self._graft = graft

    def _patch_graft(self, graft: Graft) -> None:
        """Further changes a backbone's graft makes to the policy, each through `graft` (Graft.shadow, Graft.override)
        so that `reset` undoes it: none by default."""

    def reset(self) -> None:
        """Back to the policy as loaded (`Graft.undo`), so one loaded policy serves every cell of one command (a
        released pi0.5 is 3.3B parameters: reloading it per cell costs more than a fit). Keeps no copy of
        any weight."""
        graft, self._graft = self._graft, None
        if graft is not None:
            graft.undo()

    def _feature_images(self, batch: Mapping[str, Any]) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
        """Grafted stand-in for the policy's image preparation: cached features instead of pixels."""
        feats = {k: batch.get(feature_key(k)) for k in self.camera_keys}
        first = None
        for key, f in feats.items():
            if f is None:
                raise BackboneError(f"{self.name} batch has no {feature_key(key)} (camera {key})")
            if f.ndim != 3 or f.shape[-1] != self.projector.in_features:
                raise BackboneError(
                    f"{feature_key(key)}: expected [B, T, {self.projector.in_features}] features, got {tuple(f.shape)}"
                )
            first = f if first is None else first
        images, masks = [], []
        for key in self.config.image_features:
            f = feats.get(key)
            real = f is not None
            images.append(f if real else torch.zeros_like(first))
            masks.append(torch.full((first.shape[0],), real, dtype=torch.bool, device=first.device))
        return images, masks

    def add_lora(self, rank: int, alpha: float | None = None) -> None:
        """The `lora` control: peft LoRA adapters on the language model's projections, trained together
        with the projector. The adapters are injected in place (lerobot calls the layers' projections
        directly, not the LM's forward); their B matrices start at zero, so before training the policy
        computes exactly what the plain graft does. Only the adapters become trainable in the LM."""
        from peft import LoraConfig

        if not self.grafted:
            raise BackboneError(f"{self.name}: add LoRA after graft(), so the projector and adapters train together")
        config = LoraConfig(r=rank, lora_alpha=alpha or rank, lora_dropout=0.0, bias="none",
                            target_modules=list(LORA_TARGETS))
        self._graft.add_lora(self._module_groups()["language model"], config)

    def freeze_report(self) -> FreezeReport:
        return freeze_report(self._module_groups(), self.policy)
