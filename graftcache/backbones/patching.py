"""The one way graftcache changes a lerobot (or transformers, torch) object it does not own: a recorded attribute
change, undone by restoring the original object itself.

Adapters run lerobot's own code and change as little of it as they can, but some changes are needed: a method shadowed
on a policy's module while grafted (EO-1's Qwen `get_image_features`), a module global answered with the caller's
draws for one call (graftcache.backbones.given_draws.given_noise), a module-level function rebound while a tiny policy
is constructed (graftcache.backbones.paligemma.pi05_tiny_sizes), a class attribute (GR00T's `from_pretrained`), a config
field for one call (SmolVLA's `num_steps`). Each is a `Patches.set`, which records the owner, the attribute and what
stood there before; `Patches.undo` puts back that very object (or removes the attribute where the owner had none of
its own, so the class's method shows through again), last change first.

- `Patches`: a record held as long as its changes last (a graft's: graftcache.backbones.surgery.Graft);
- `patched(owner, **values)`: the changes for the duration of a block;
- `observe()`: every change made inside a block, as `Change` records, whether undone or not (what the tests check
  against: after reset every owner holds its original again).
"""

from __future__ import annotations

import contextlib
import functools
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

from torch import nn

#: The observers of `observe()` blocks now open (each a list collecting every change made).
_observers: list[list[Change]] = []


@dataclass(frozen=True)
class Change:
    """One recorded attribute change: `original` is what `owner.attribute` was (`own` False: the owner had no
    attribute of its own there, the class's showed through)."""

    owner: Any
    attribute: str
    original: Any
    own: bool

    def restore(self) -> None:
        """Put the original back (or remove the owner's own attribute where it had none)."""
        if self.own:
            setattr(self.owner, self.attribute, self.original)
        elif self.attribute in vars(self.owner):
            delattr(self.owner, self.attribute)

    def is_restored(self) -> bool:
        """Whether `owner.attribute` is the original object again (identity), or absent again."""
        if not self.own:
            return self.attribute not in vars(self.owner)
        return _current(self.owner, self.attribute) is self.original


def _is_submodule_slot(owner: Any, attribute: str) -> bool:
    return isinstance(owner, nn.Module) and any(attribute in getattr(owner, slots, {}) for slots in
                                                 ("_modules", "_parameters", "_buffers"))


def _current(owner: Any, attribute: str) -> Any:
    """What stands at `owner.attribute` as the owner holds it: a submodule slot's module, else the raw entry of the
    owner's own namespace (a class's classmethod object, not the bound method)."""
    return getattr(owner, attribute) if _is_submodule_slot(owner, attribute) else vars(owner)[attribute]


class Patches:
    """Changes to objects graftcache does not own, each recorded with what it replaced; `undo()` restores them all."""

    def __init__(self) -> None:
        self.changes: list[Change] = []

    def set(self, owner: Any, attribute: str, value: Any) -> None:
        """`setattr(owner, attribute, value)`, recorded."""
        own = _is_submodule_slot(owner, attribute) or attribute in vars(owner)
        change = Change(owner, attribute, _current(owner, attribute) if own else None, own)
        self.changes.append(change)
        for observer in _observers:
            observer.append(change)
        setattr(owner, attribute, value)

    def shadow(self, module: nn.Module, name: str, replacement: Callable) -> None:
        """Shadow `module.name` on the instance with `replacement(own, module, *args, **kwargs)`, `own` being the
        class's method (the replacement falls back to it)."""
        self.set(module, name, functools.partial(replacement, getattr(type(module), name), module))

    def undo(self) -> None:
        """Every change undone, the last one first."""
        while self.changes:
            self.changes.pop().restore()


@contextlib.contextmanager
def patched(owner: Any, **values: Any) -> Iterator[None]:
    """`owner`'s attributes set to `values` for the duration of the block (instance attributes shadowing methods, a
    module's globals, a class's attributes, a config's fields), then the originals back."""
    patches = Patches()
    try:
        for attribute, value in values.items():
            patches.set(owner, attribute, value)
        yield
    finally:
        patches.undo()


@contextlib.contextmanager
def observe() -> Iterator[list[Change]]:
    """Every change any `Patches` makes while the block runs, in order (a list filled as they happen)."""
    seen: list[Change] = []
    _observers.append(seen)
    try:
        yield seen
    finally:
        _observers.remove(seen)
