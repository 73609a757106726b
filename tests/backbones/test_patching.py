"""Every change an adapter makes to lerobot goes through one recorded mechanism (graftcache.backbones.patching), which
undoes a patch to the very object it replaced. That reset() undoes every backbone's changes is the contract's
(tests/backbones/test_contract.py)."""

from __future__ import annotations

import pytest

from graftcache.backbones.patching import Patches, observe, patched

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # tests/fixtures/torch_threads.py


def test_a_patch_is_undone_to_the_very_object_it_replaced() -> None:
    class Owner:
        def method(self) -> str:
            return "own"

    owner, value = Owner(), object()
    with observe() as changes, patched(Owner, constant=value), patched(owner, method=lambda: "shadow"):
        assert Owner.constant is value and owner.method() == "shadow"
    assert not hasattr(Owner, "constant") and "method" not in vars(owner) and owner.method() == "own"
    assert [c.attribute for c in changes] == ["constant", "method"] and all(c.is_restored() for c in changes)
    patches, original = Patches(), vars(Owner)["method"]
    patches.set(Owner, "method", lambda self: "class patch")
    assert owner.method() == "class patch"
    patches.undo()
    assert vars(Owner)["method"] is original and not patches.changes
