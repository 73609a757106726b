"""Every change an adapter makes to lerobot goes through one recorded mechanism (graftcache.backbones.patching) and
reset() undoes it: for every registered backbone, after load -> graft -> fit steps -> reset, each lerobot module
global, class attribute and policy attribute is the original object again, and the weights are a fresh load's."""

from __future__ import annotations

import sys

import pytest
import torch
from helpers.backbones import ENC_DIM, raw_features, tiny

from graftcache.backbone_table import BACKBONES
from graftcache.backbones.checkpoint import state_dict_sha256
from graftcache.backbones.patching import Patches, observe, patched
from graftcache.graft import GraftProjector

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # tests/fixtures/torch_threads.py


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


@pytest.mark.parametrize("name", sorted(BACKBONES))
def test_reset_gives_back_every_lerobot_object_and_the_loaded_weights(name: str) -> None:
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
        if adapter.can_checkpoint:
            adapter.set_activation_checkpointing(True)
            adapter.loss(batch).mean().backward()
            adapter.set_activation_checkpointing(False)
        adapter.reset()
    assert changes, "a graft changes the policy (its image method at least), through graftcache.backbones.patching"
    assert [(c.owner, c.attribute) for c in changes if not c.is_restored()] == []
    after = lerobot_objects(adapter.policy)
    changed = sorted(k for k, v in before.items() if k in after and after[k] is not v)
    added = sorted(k for k in after if k not in before and k[0] in ("policy", "config"))
    assert changed == [] and added == []
    assert [k for k in after if k[0] == "policy"] == [], "a method shadowed on the policy outlives reset"
    assert state_dict_sha256(adapter.policy) == state_dict_sha256(tiny(name).policy)
