"""Graft surgery on a backbone: tower -> pass-through, connector -> projector, freezing, LoRA, undo.

The backbone's vision tower is replaced by `PassThroughTower` (so lerobot's own `embed_image` runs
unchanged and simply receives cached features) and its connector by the projector; everything but the
projector is frozen. `reset` undoes all of it, so one loaded policy serves every cell of a run.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

import torch
from torch import nn
from transformers.modeling_outputs import BaseModelOutput

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


class GraftSurgery:
    """The surgery half of a BackboneAdapter (mixed into it; uses its policy, device and slots)."""

    @property
    def grafted(self) -> bool:
        return self.projector is not None

    def graft(self, projector: nn.Module) -> None:
        """Replace tower and connector, read images from cached features, freeze all but `projector`."""
        if self.grafted:
            raise BackboneError(f"{self.name}: already grafted")
        width = getattr(projector, "out_features", None)
        if width != self.lm_width:
            raise BackboneError(f"{self.name}: projector outputs width {width}, the LM expects {self.lm_width}")
        _ = self.policy_sha256  # pin the hash of the loaded weights before the surgery changes them
        if self._pristine is None:
            self._pristine = {k: v.detach().to("cpu", copy=True) for k, v in self.policy.state_dict().items()}
        self._requires_grad = {n: p.requires_grad for n, p in self.policy.named_parameters()}
        owner, tower, connector = self._vision_slots()
        projector = projector.to(self.device)
        self._replace(owner, tower, PassThroughTower().to(self.device))
        self._replace(owner, connector, projector)
        setattr(self.policy, self.image_method, self._feature_images)
        freeze_all_but(self.policy, projector)
        self.projector = projector

    def _replace(self, owner: nn.Module, attribute: str, module: nn.Module) -> None:
        """setattr that remembers the module it replaced, so reset() can undo the surgery."""
        self._undo.append((owner, attribute, getattr(owner, attribute)))
        setattr(owner, attribute, module)

    def reset(self) -> None:
        """Back to the policy as loaded: undo graft and LoRA surgery, restore the requires_grad flags and
        the weights from the CPU copy kept at the first graft(). Lets one loaded backbone serve every
        cell of a run (a released pi0.5 is 3.3B parameters: reloading it per cell costs more than a fit)."""
        while self._undo:
            owner, attribute, original = self._undo.pop()
            setattr(owner, attribute, original)
        self.policy.__dict__.pop(self.image_method, None)  # the instance override set by graft()
        if self._lora_host is not None:
            self._lora_host.__dict__.pop("peft_config", None)
            self._lora_host = None
        for name, param in self.policy.named_parameters():
            param.requires_grad_(self._requires_grad.get(name, param.requires_grad))
        if self._pristine is not None:
            self.policy.load_state_dict(self._pristine, strict=True)
        self.projector = None

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
        from peft import LoraConfig, inject_adapter_in_model

        if not self.grafted:
            raise BackboneError(f"{self.name}: add LoRA after graft(), so the projector and adapters train together")
        lm = self._module_groups()["language model"]
        config = LoraConfig(r=rank, lora_alpha=alpha or rank, lora_dropout=0.0, bias="none",
                            target_modules=list(LORA_TARGETS))
        inject_adapter_in_model(config, lm)
        self._lora_host = lm  # peft records its config on the module: dropped again by reset()
        for owner in list(lm.modules()):
            for attribute, child in list(owner.named_children()):
                base = getattr(child, "base_layer", None)
                if isinstance(base, nn.Module):  # a peft LoRA layer wrapping the original projection
                    self._undo.append((owner, attribute, base))
        for name, param in lm.named_parameters():
            param.requires_grad_("lora_" in name)

    def freeze_report(self) -> FreezeReport:
        return freeze_report(self._module_groups(), self.policy)
