"""lerobot 0.6's pi0.5 on stock transformers: its training path and its KV-cache inference path agree."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from helpers.backbones import activation_checkpointing_peaks, grafted, raw_images, tiny
from helpers.policies import assert_same_policy, lerobot_from_pretrained, tensors

from graftcache.backbones import load_backbone
from graftcache.backbones.batches import TOKEN_MASK, TOKENS

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # tests/fixtures/torch_threads.py


def _velocities(adapter, x_t: torch.Tensor, time: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, int, int]:
    """v_t from the training path (one joint prefix+suffix pass, as PI05Pytorch.forward) and from the
    inference path (prefix KV cache, then denoise_step, as PI05Pytorch.sample_actions)."""
    from lerobot.policies.common.vla_utils import make_att_2d_masks, prepare_attention_masks_4d

    model, chunk = adapter.policy.model, adapter.chunk_size
    batch = adapter.prepare(raw_images(adapter, x_t.shape[0]))
    images, img_masks = adapter.policy._preprocess_images(batch)
    prefix, prefix_pad, prefix_att = model.embed_prefix(images, img_masks, batch[TOKENS], batch[TOKEN_MASK])
    suffix, suffix_pad, suffix_att, cond = model.embed_suffix(x_t, time)

    pad, att = torch.cat([prefix_pad, suffix_pad], 1), torch.cat([prefix_att, suffix_att], 1)
    (_, out), _ = model.paligemma_with_expert.forward(
        attention_mask=prepare_attention_masks_4d(make_att_2d_masks(pad, att)),
        position_ids=torch.cumsum(pad, 1) - 1, past_key_values=None, inputs_embeds=[prefix, suffix],
        use_cache=False, adarms_cond=[None, cond],
    )
    v_train = model.action_out_proj(out[:, -chunk:].float())

    model.paligemma_with_expert.paligemma.model.language_model.config._attn_implementation = "eager"
    _, cache = model.paligemma_with_expert.forward(
        attention_mask=prepare_attention_masks_4d(make_att_2d_masks(prefix_pad, prefix_att)),
        position_ids=torch.cumsum(prefix_pad, 1) - 1, past_key_values=None, inputs_embeds=[prefix, None],
        use_cache=True,
    )
    cached = cache.get_seq_length()
    v_infer = model.denoise_step(prefix_pad, cache, x_t, time)
    return v_train, v_infer, cached, cache.get_seq_length()


def test_training_and_kv_cache_paths_give_the_same_velocity() -> None:
    adapter = tiny("pi05")
    for name, p in adapter.policy.named_parameters():
        if ".dense." in name:  # adaRMS modulation: make scale, shift and gate all matter
            torch.nn.init.normal_(p, std=0.1)
    adapter.policy.eval()
    g = torch.Generator().manual_seed(0)
    x_t = torch.randn(3, adapter.chunk_size, adapter.max_action_dim, generator=g)
    with torch.no_grad():
        v_train, v_infer, cached, after = _velocities(adapter, x_t, torch.full((3,), 0.37))
        v_later, _, _, _ = _velocities(adapter, x_t, torch.full((3,), 0.8))
    assert cached == after > 0  # denoising read the prefix cache without appending to it
    torch.testing.assert_close(v_infer, v_train, atol=2e-5, rtol=1e-4)
    assert (v_later - v_train).abs().max() > 1e-3  # the time condition reaches the expert


def test_activation_checkpointing_lowers_the_peak() -> None:
    plain, checkpointed = activation_checkpointing_peaks(grafted("pi05"))
    assert checkpointed < 0.85 * plain, (checkpointed, plain)  # measured: 51% of the plain step's peak


def test_lean_load_casts_as_lerobot_does_when_the_config_asks_for_bfloat16(tmp_path: Path) -> None:
    """pi0.5's config asking for bf16 (LM cast, vision path and norms fp32): each tensor is cast on the way in, as
    load_state_dict's copy casts, and the result is lerobot's from_pretrained bit for bit."""
    folder = tiny("pi05", seed=2).save(tmp_path / "ckpt")
    config = json.loads((folder / "config.json").read_text())
    (folder / "config.json").write_text(json.dumps({**config, "dtype": "bfloat16"}))
    reference = lerobot_from_pretrained("pi05", folder)
    lean = load_backbone("pi05", folder).policy
    assert_same_policy(lean, reference)
    assert {t.dtype for t in tensors(lean).values()} >= {torch.bfloat16, torch.float32}
