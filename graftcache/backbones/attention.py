"""The frozen LM's and action expert's attention: lerobot's eager path, or the fused one (`fit --attention`).

lerobot runs pi0 / pi0.5 attention eagerly (it sets `_attn_implementation = "eager"` before every call and its joint
layer calls `modeling_gemma.eager_attention_forward` itself) and SmolVLA through its own `eager_attention_forward`:
each materialises every [B, heads, L, L] score and probability matrix, for the forward and again for backward. The
fused path computes the same attention with `torch.nn.functional.scaled_dot_product_attention` (one kernel that keeps
no matrix where the device has one), given the same additive mask in the query's dtype (a bool mask would make rows
that see no key NaN where eager's finite "minus infinity" makes them uniform; a mask of another dtype sends CUDA to
the math kernel), the same scaling and the same grouped keys and values. It is installed through
graftcache.backbones.patching like every other change to lerobot, per backbone by its `_switch_attention` hook, and
undone to go back to lerobot's own. Which paths a backbone has is its spec's `attentions`, lerobot's own first: pi0,
pi0.5 and SmolVLA eager then sdpa; pi0-FAST, which lerobot leaves at transformers' sdpa, sdpa then eager; the others
one path, what lerobot builds their LM with (EO-1, GR00T, VLA-JEPA, X-VLA: sdpa; EVO1's InternVL and Wall-X's Qwen MoE,
which refuses any other: eager).

The two paths compute one function in different orders: they agree within `TOLERANCE` (per compute dtype;
tests/backbones/test_attention.py), which is why the path is recorded in rows (`attention`) but enters no run_id.
"""

from __future__ import annotations

import torch
from torch.nn import functional

from graftcache.backbones.patching import Patches
from graftcache.backbones.spec import FUSED as FUSED  # re-exported: where the attention paths are named
from graftcache.errors import BackboneError

EAGER = "eager"  # lerobot's own path for most backbones; FUSED (from the spec) is torch's
#: How far the fused path's loss, projector gradients and predicted chunk may be from eager's under the same draws and
#: weights, per compute dtype: |fused - eager| / |eager| (the norms of the whole tensor). fp32: summation order only
#: (measured on the tiny backbones: <= 5e-6); bf16: eager rounds its probabilities to bf16 before multiplying by the
#: values and the kernel does not (measured <= 8e-3 on the gradients, less than bf16 itself moves eager from fp32).
TOLERANCE = {"fp32": 1e-5, "bf16": 2e-2}
#: What a masked score gets added: openpi's "minus infinity" (lerobot's OPENPI_ATTENTION_MASK_VALUE), finite in fp32
#: and bf16, so a row that sees no key averages every value as eager's does instead of becoming NaN.
MASKED = -2.3819763e38


def fused_attention(query: torch.Tensor, key: torch.Tensor, value: torch.Tensor, additive_mask: torch.Tensor | None,
                    scaling: float, dropout: float = 0.0) -> torch.Tensor:
    """softmax(q k^T * scaling + mask) v for [B, heads, L, D] queries and [B, kv_heads, S, D] keys and values, each key
    head serving its group of heads // kv_heads query heads, as transformers' repeat_kv does; returns [B, heads, L,
    D]. The keys and values are repeated rather than passed with `enable_gqa`: CUDA has no masked kernel for that
    (the math kernel would run), which is why transformers' own sdpa attention repeats them where there is a mask."""
    groups = query.shape[1] // key.shape[1]
    if groups > 1:
        key, value = key.repeat_interleave(groups, dim=1), value.repeat_interleave(groups, dim=1)
    if additive_mask is not None:
        additive_mask = additive_mask.to(query.dtype)
    return functional.scaled_dot_product_attention(query, key.to(query.dtype), value.to(query.dtype),
                                                   attn_mask=additive_mask, dropout_p=dropout, scale=scaling)


class Attention:
    """The attention half of a BackboneAdapter (mixed into it): one switch, lerobot's own attention after load.

    Which paths a backbone has is data on its spec (`BackboneSpec.attentions`, lerobot's own first); getting from
    lerobot's own to another is its `_switch_attention` hook. The switch is made again at the start of every pass
    (graftcache.fit.run), so a policy whose fused path shares a lerobot module global with another loaded policy
    (pi0 and pi0.5: modeling_gemma's) finds it installed whichever of them switched last."""

    @property
    def attention(self) -> str:
        """What the frozen LM and expert attend with now: "eager" or "sdpa"."""
        return self.__dict__.get("_attention", self.spec.attentions[0])

    @classmethod
    def resolve_attention(cls, mode: str) -> str:
        """`auto` -> the fused path where this backbone has one, else lerobot's own; an explicit path this backbone
        lacks is refused in one line."""
        return cls.spec.resolve_attention(cls.name, mode)

    def set_attention(self, mode: str) -> str:
        """Attend with `mode` (auto, eager or sdpa) from whatever state the policy is in, and return what it resolved
        to. Activation checkpointing wraps the attention as it stands, so the recompute plan is set off around the
        switch and put back after it."""
        resolved = self.resolve_attention(mode)
        plan = self.recompute_plan
        self.set_recompute_plan("off")
        self.attention_patches.undo()
        if resolved != self.spec.attentions[0]:
            self._switch_attention(self.attention_patches, resolved)
        self.__dict__["_attention"] = resolved
        self.set_recompute_plan(plan)
        return resolved

    def _switch_attention(self, patches: Patches, mode: str) -> None:
        """Make the policy attend with `mode`, another of `spec.attentions` than lerobot's own, through `patches`
        (a backbone that declares one path has no such hook)."""
        raise BackboneError(f"{self.name}: no attention but lerobot's own ({self.spec.attentions[0]})")

    @property
    def attention_patches(self) -> Patches:
        """What switching the attention changed in lerobot (graftcache.backbones.patching), undone to go back."""
        return self.__dict__.setdefault("_attention_patches", Patches())
