"""Activation checkpointing of the frozen language model and action expert. graftcache's switch of it is
"recompute": whether a backbone can (`BackboneSpec.can_recompute`), whether an adapter does now (`recomputing`,
`set_recompute`) and what a fit asks (`fit --recompute auto|on|off`).

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
"""

from __future__ import annotations

from abc import abstractmethod
from collections.abc import Callable, Iterator

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


class ActivationCheckpointing:
    """The activation checkpointing half of a BackboneAdapter (mixed into it): one switch, `set_recompute`, off
    after load."""

    _recomputing: bool = False

    @property
    def recomputing(self) -> bool:
        """Whether the frozen LM and expert recompute their activations during backward now."""
        return self._recomputing

    def set_recompute(self, on: bool) -> None:
        """Turn recomputing on or off in the model itself, whatever state it is in (lerobot's own switch may have
        turned it on), so that the flag rows record is what runs; the numbers do not change, only the memory a
        training step holds and the FLOPs it spends."""
        if on or self.spec.can_recompute:
            self._switch_recompute(on)
        self._recomputing = on

    def _switch_recompute(self, on: bool) -> None:
        """The backbone's own way of turning activation checkpointing of its LM and expert on or off, from whatever
        state (none by default: `auto` then keeps it off, `on` is refused in one line)."""
        raise BackboneError(f"{self.name}: no activation checkpointing for this backbone; use --recompute "
                            "off")

    @property
    def recompute_patches(self) -> Patches:
        """What turning recomputing on changed in the policy (graftcache.backbones.patching), undone to turn it
        off."""
        return self.__dict__.setdefault("_recompute_patches", Patches())


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
