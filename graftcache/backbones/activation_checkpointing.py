"""Activation checkpointing of the frozen language model and action expert. graftcache's switch of it is
"recompute": whether a backbone can (`BackboneSpec.can_recompute`), whether an adapter does now (`recomputing`,
`set_recompute`, `recompute_plan`) and what a fit asks (`fit --recompute auto|off|mlp|on`).

A graft trains only the projector, but its gradient flows back through every layer of the frozen LM and expert,
so a step keeps every layer's activations for backward: at released size and the paper's batch of 32 that is
more than a GPU holds. Checkpointed, a layer keeps its inputs and recomputes the rest during backward (one more
forward's FLOPs; the gradients are the same).

How each backbone does it: pi0.5 and pi0 with lerobot's own `gradient_checkpointing_enable` (every LM + expert
layer, the final norms and the prefix/suffix embeddings, in training mode). lerobot's SmolVLA has no such switch,
and transformers' `gradient_checkpointing_enable` on its VLM does nothing on its path (smolvlm_with_expert.py calls
each layer's parts directly, never the layer, which is where transformers checkpoints), so here the attention
(`eager_attention_forward`, whose fp32 [B, heads, L, L] probabilities dominate) and the MLP of every LM and expert
layer are wrapped in `torch.utils.checkpoint`, in training mode with gradients enabled, like lerobot's. X-VLA the
same way: every layer of its BART encoder (the LM) and every block of its action transformer.

Recompute plans (`PLANS`, least recompute first; `fit --recompute` names one, or `auto`): `off` keeps
every activation; `mlp` recomputes only each LM and expert layer's MLP (`_mlp_slots`, wrapped as above); `on` is the
whole layer, as described above. Why `mlp` is a plan of its own, from the geometry (per token and layer, a frozen
Linear keeps no input since its weight needs no gradient, so a gated MLP keeps its gate, its activation and its up
projection, 3 x ffn values, while eager attention keeps q, k, v, its fp32 scores and their bf16 copy, about
(heads + kv heads) x head_dim + 1.5 x heads x L x 4 bytes, plus the norms' fp32 inputs): at pi0.5's released Gemma
2B (width 2048, ffn 16384, 8 heads of 256, 1 KV head, L ~ 970 prefix tokens) the MLP holds ~98 KB of ~165 KB a
token, about 0.6 of what a layer keeps, and costs ~0.88 of the layer's forward FLOPs to recompute (3 x width x ffn
against the attention's 4.3 x width^2 + 2 x L x heads x head_dim). The fit does not trust the model for bytes: the
step is measured under each plan it tries (graftcache/fit/step_memory.py).
"""

from __future__ import annotations

from abc import abstractmethod
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import torch
from torch import nn
from torch.utils.checkpoint import checkpoint

from graftcache.backbones.patching import Patches
from graftcache.errors import BackboneError


def checkpointed(fn: Callable, owner: nn.Module) -> Callable:
    """`fn` recomputed during backward (non-reentrant, so a graft's trainable parameters inside it still get
    their gradients) while `owner` trains with gradients enabled; plain `fn` otherwise (evaluation). The RNG
    state is replayed for the recomputation: X-VLA's layers train with dropout, whose masks must not change."""

    def run(*args, **kwargs):
        if owner.training and torch.is_grad_enabled():
            return checkpoint(fn, *args, use_reentrant=False, preserve_rng_state=True, **kwargs)
        return fn(*args, **kwargs)

    return run


@dataclass(frozen=True)
class RecomputePlan:
    """What a training step recomputes in backward instead of keeping: `phrase` completes "a training step ..." in
    refusals; `install` makes the change on an adapter whose plan is off; `available` says which backbones have it."""

    phrase: str
    install: Callable[[ActivationCheckpointing], None]
    available: Callable[[ActivationCheckpointing], bool]


def _recompute_mlps(adapter: ActivationCheckpointing) -> None:
    for owner, attribute in adapter._mlp_slots():
        adapter.recompute_plan_patches.set(owner, attribute, checkpointed(getattr(owner, attribute), owner))


def _has_mlp_slots(adapter: ActivationCheckpointing) -> bool:
    return type(adapter)._mlp_slots is not ActivationCheckpointing._mlp_slots


#: The recompute plans, least recompute first (graftcache.requests.RECOMPUTE_PLANS names them for the CLI; tests
#: keep the two equal): `--recompute auto` takes the first one the backbone has whose step fits.
PLANS: dict[str, RecomputePlan] = {
    "off": RecomputePlan("", lambda adapter: None, lambda adapter: True),
    "mlp": RecomputePlan(" with activation checkpointing of each layer's MLP", _recompute_mlps, _has_mlp_slots),
    "on": RecomputePlan(" with activation checkpointing", lambda adapter: adapter._switch_recompute(True),
                        lambda adapter: adapter.spec.can_recompute),
}


class ActivationCheckpointing:
    """The activation checkpointing half of a BackboneAdapter (mixed into it): one recompute plan, off after load;
    `set_recompute` the switch between `on` and `off`."""

    _recompute_plan: str = "off"

    @property
    def recompute_plan(self) -> str:
        """The plan of `PLANS` a training step runs under."""
        return self._recompute_plan

    @property
    def recompute_plans(self) -> tuple[str, ...]:
        """The plans this backbone has, least recompute first."""
        return tuple(name for name, plan in PLANS.items() if plan.available(self))

    @property
    def recomputing(self) -> bool:
        """Whether the frozen LM and expert recompute any activations during backward now (a plan other than off)."""
        return self._recompute_plan != "off"

    def set_recompute_plan(self, plan: str) -> None:
        """Put the model under `plan` whatever state it is in (lerobot's own switch may have turned recomputing on),
        so that what rows record is what runs; the numbers do not change, only the memory a training step holds and
        the FLOPs it spends. A plan this backbone lacks is refused in one line."""
        if plan not in self.recompute_plans:
            raise BackboneError(f"{self.name}: no recompute plan {plan!r} for this backbone; use "
                                f"--recompute {' or '.join(self.recompute_plans)}")
        self.recompute_plan_patches.undo()
        if self.spec.can_recompute:
            self._switch_recompute(False)
        PLANS[plan].install(self)
        self._recompute_plan = plan

    def set_recompute(self, on: bool) -> None:
        """The plan `on` (every layer recomputed) or `off`."""
        self.set_recompute_plan("on" if on else "off")

    def _switch_recompute(self, on: bool) -> None:
        """The backbone's own way of turning activation checkpointing of its whole LM and expert layers on or off,
        from whatever state (none by default: the plan `on` is then refused in one line)."""
        raise BackboneError(f"{self.name}: no activation checkpointing for this backbone; use --recompute "
                            "off")

    def _mlp_slots(self) -> Iterator[tuple[nn.Module, str]]:
        """(module, attribute) of each LM and expert layer's MLP forward, which the plan `mlp` recomputes (none by
        default: the backbone has no such plan)."""
        return iter(())

    @property
    def recompute_patches(self) -> Patches:
        """What turning recomputing on changed in the policy (graftcache.backbones.patching), undone to turn it
        off."""
        return self.__dict__.setdefault("_recompute_patches", Patches())

    @property
    def recompute_plan_patches(self) -> Patches:
        """What a plan other than `on` changed in the policy (the `mlp` plan's wrappers), undone by the next plan."""
        return self.__dict__.setdefault("_recompute_plan_patches", Patches())


class WrappedActivationCheckpointing(ActivationCheckpointing):
    """Activation checkpointing by wrapping callables given as (owner module, attribute) pairs: an instance
    attribute shadows the class's method while on (recorded in `recompute_patches`), undone to turn it
    off."""

    @abstractmethod
    def _recompute_slots(self) -> Iterator[tuple[nn.Module, str]]:
        """(module, attribute) of every callable to checkpoint, e.g. (layer.mlp, "forward")."""

    def _switch_recompute(self, on: bool) -> None:
        patches = self.recompute_patches
        if not on:
            patches.undo()
            return
        if patches.changes:
            return  # wrapped once, however often it is turned on
        for owner, attribute in self._recompute_slots():
            patches.set(owner, attribute, checkpointed(getattr(owner, attribute), owner))
