"""pi0 as a backbone, with pi0-FAST where they share PaliGemma: both policies' released geometry on the meta device
(3-4B parameters are never materialised here: shapes only, counted against the architectures' own formulas) and
what activation checkpointing saves. pi0-FAST's own policy loss: tests/backbones/test_pi0_fast.py."""

from __future__ import annotations

import pytest
import torch
from helpers.backbones import ENC_DIM, activation_checkpointing_peaks, grafted

from graftcache.graft import GraftProjector, feature_key

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # tests/fixtures/torch_threads.py


# ---------------------------------------------------------------------------------------------- released geometry
def _siglip(width: int, mlp: int, depth: int, patch: int, image: int) -> int:
    """Parameters of a SigLIP vision tower (patch conv, position table, pre-norm blocks, post norm)."""
    block = 4 * (width * width + width) + (width * mlp + mlp) + (mlp * width + width) + 2 * 2 * width
    return depth * block + (3 * patch * patch * width + width) + (image // patch) ** 2 * width + 2 * width


def _gemma(width: int, depth: int, mlp: int, heads: int, kv: int, head: int, vocab: int | None) -> int:
    """Parameters of a Gemma decoder (bias-free attention and gated MLP, RMS norms, optional token table)."""
    block = width * heads * head * 2 + width * kv * head * 2 + 3 * width * mlp + 2 * width
    return depth * block + width + (vocab * width if vocab else 0)


VOCAB = 257152  # PaliGemma's, hard-coded by lerobot (modeling_pi0.py:216)
TOWER = _siglip(1152, 4304, 27, 14, 224)  # So400m/14 at 224 px
CONNECTOR = 1152 * 2048 + 2048
GEMMA_2B = _gemma(2048, 18, 16384, 8, 1, 256, VOCAB)
EXPERT = _gemma(1024, 18, 4096, 8, 1, 256, None) + VOCAB * 1024  # gemma_300m: no token table, its own lm_head


def _released(name: str):
    """lerobot's own constructor at the released geometry (LIBERO's cameras and dims, chunk 50, pi0 with the
    LIBERO recipe's masked third slot), on the meta device, wrapped in the adapter."""
    from devtools.released import LIBERO, _construct_on_meta, _features, unit_stats
    from graftcache.backbones import get_backbone
    from graftcache.backbones.pi0_fast.fast import policy_tokenizers
    from graftcache.backbones.pi0_fast.tiny import fit_tiny_fast
    from graftcache.backbones.tiny import TinyBuild
    from graftcache.backbones.tiny_assets import PALIGEMMA_DIR

    inputs, outputs = _features(LIBERO)
    if name == "pi0":
        from lerobot.policies.pi0.configuration_pi0 import PI0Config
        from lerobot.policies.pi0.modeling_pi0 import PI0Policy

        config = PI0Config(dtype="bfloat16", empty_cameras=1, device="cpu", input_features=inputs,
                           output_features=outputs)
        policy = _construct_on_meta(PI0Policy, config, torch.bfloat16)
    else:
        from lerobot.policies.pi0_fast.configuration_pi0_fast import PI0FastConfig
        from lerobot.policies.pi0_fast.modeling_pi0_fast import PI0FastPolicy

        config = PI0FastConfig(dtype="bfloat16", device="cpu", input_features=inputs, output_features=outputs)
        # construction reads none of the tokenizer's fit
        fast = fit_tiny_fast(unit_stats(LIBERO), TinyBuild(chunk_size=config.chunk_size))
        with policy_tokenizers(fast, PALIGEMMA_DIR):
            policy = _construct_on_meta(PI0FastPolicy, config, torch.bfloat16)
    adapter = get_backbone(name)(policy, None, None, source="meta", random_init=True)
    adapter._sha256, adapter._pristine = "meta", {}  # graft() pins a hash and keeps a copy: nothing to read on meta
    return adapter


@pytest.mark.parametrize(("name", "slots", "others"), [
    ("pi0", ("image", "image2", "empty_camera_0"), {
        "action expert": EXPERT, "state projection": 32 * 1024 + 1024,  # max_state_dim 32 -> expert width
        # action_in_proj, action_out_proj (max_action_dim 32 <-> 1024), action_time_mlp_in (2048 -> 1024), _out
        "action/time projections": (32 * 1024 + 1024) + (1024 * 32 + 32) + (2048 * 1024 + 1024)
        + (1024 * 1024 + 1024)}),
    ("pi0_fast", ("image", "image2"), {}),
])
def test_released_geometry_on_the_meta_device(name: str, slots: tuple[str, ...], others: dict) -> None:
    adapter = _released(name)
    policy = adapter.policy
    groups = {k: sum(p.numel() for m in (v if isinstance(v, tuple) else (v,)) for p in m.parameters())
              for k, v in adapter._module_groups().items()}
    lm_head = VOCAB * 2048  # PaliGemma's own lm_head (pi0-FAST decodes with it; pi0 never uses it)
    expected = {"vision tower": TOWER, "connector": CONNECTOR, "language model": GEMMA_2B, **others}
    if name == "pi0_fast":
        expected["LM head"] = lm_head
    assert {k: groups[k] for k in expected} == expected
    total = sum(p.numel() for p in policy.parameters())
    assert total == sum(expected.values()) + (lm_head if name == "pi0" else 0)
    assert total == {"pi0": 4_028_019_472, "pi0_fast": 3_449_982_704}[name]

    assert adapter.token_grid == (16, 16) and adapter.lm_width == 2048 and adapter.embed_scale == 1.0
    assert tuple(k.removeprefix("observation.images.") for k in adapter.config.image_features) == slots
    assert adapter.cameras == ("image", "image2")
    tower, connector = adapter._tower_and_connector()
    hidden = tower(torch.empty(2, 3, 224, 224, device="meta")).last_hidden_state
    assert tuple(hidden.shape) == (2, 256, 1152) and tuple(connector(hidden).shape) == (2, 256, 2048)

    adapter.graft(GraftProjector(ENC_DIM, adapter.lm_width))
    features = {feature_key(c): torch.zeros(2, 256, ENC_DIM) for c in adapter.cameras}
    images, masks = getattr(policy, adapter.image_method)(features)  # the grafted slots, real values on the CPU
    assert [tuple(i.shape) for i in images] == [(2, 256, ENC_DIM)] * len(slots)
    assert [m.tolist() for m in masks] == [[True, True], [True, True], [False, False]][:len(slots)]
    meta = [i.to("meta") for i in images]
    tokens, token_mask = torch.zeros(2, 12, dtype=torch.long, device="meta"), torch.ones(2, 12, dtype=torch.bool,
                                                                                         device="meta")
    embed = policy.model.embed_prefix if name == "pi0" else policy.model.embed_prefix_fast
    embs = embed(meta, [m.to("meta") for m in masks], tokens, token_mask)[0]
    assert tuple(embs.shape) == (2, 256 * len(slots) + 12, 2048)  # 256 tokens x 2048 per slot, then the prompt


@pytest.mark.parametrize("name", ["pi0", "pi0_fast"])
def test_activation_checkpointing_lowers_the_peak(name: str) -> None:
    plain, checkpointed = activation_checkpointing_peaks(grafted(name))
    assert checkpointed < 0.85 * plain, (checkpointed, plain)
