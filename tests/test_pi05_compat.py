"""pi05_compat: lerobot's pi0.5 on stock transformers, and only when the transformers fork is absent."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import torch
from backbones_fixtures import one_torch_thread, raw_images, tiny  # noqa: F401  (autouse fixture)

from graftcache.backbones.base import TOKEN_MASK, TOKENS


def _velocities(adapter, x_t: torch.Tensor, time: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, int, int]:
    """v_t from the training path (one joint prefix+suffix pass, as PI05Pytorch.forward) and from the
    inference path (prefix KV cache, then denoise_step, as PI05Pytorch.sample_actions)."""
    from lerobot.policies.pi05.modeling_pi05 import make_att_2d_masks

    model, chunk = adapter.policy.model, adapter.chunk_size
    batch = adapter.prepare(raw_images(adapter, x_t.shape[0]))
    images, img_masks = adapter.policy._preprocess_images(batch)
    prefix, prefix_pad, prefix_att = model.embed_prefix(images, img_masks, batch[TOKENS], batch[TOKEN_MASK])
    suffix, suffix_pad, suffix_att, cond = model.embed_suffix(x_t, time)

    pad, att = torch.cat([prefix_pad, suffix_pad], 1), torch.cat([prefix_att, suffix_att], 1)
    (_, out), _ = model.paligemma_with_expert.forward(
        attention_mask=model._prepare_attention_masks_4d(make_att_2d_masks(pad, att)),
        position_ids=torch.cumsum(pad, 1) - 1, past_key_values=None, inputs_embeds=[prefix, suffix],
        use_cache=False, adarms_cond=[None, cond],
    )
    v_train = model.action_out_proj(out[:, -chunk:].float())

    model.paligemma_with_expert.paligemma.language_model.config._attn_implementation = "eager"
    _, cache = model.paligemma_with_expert.forward(
        attention_mask=model._prepare_attention_masks_4d(make_att_2d_masks(prefix_pad, prefix_att)),
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


def _run(code: str) -> str:
    result = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True,
                            timeout=120)
    assert result.returncode == 0, result.stderr[-2000:]
    return result.stdout


def test_compat_layer_is_not_applied_when_the_fork_is_present() -> None:
    out = _run("""
        import inspect, sys, types
        sys.modules["transformers.models.siglip.check"] = types.ModuleType("transformers.models.siglip.check")
        from transformers.models.gemma import modeling_gemma as mg
        from transformers.models.paligemma import modeling_paligemma as mp
        stock = (mg.GemmaRMSNorm.forward, mg.GemmaModel.forward, mp.PaliGemmaModel.get_image_features)
        from graftcache.backbones.pi05_compat import ensure_pi05_runtime, fork_present, installed
        assert fork_present() and ensure_pi05_runtime() is False and not installed()
        assert (mg.GemmaRMSNorm.forward, mg.GemmaModel.forward, mp.PaliGemmaModel.get_image_features) == stock
        assert "cond" not in inspect.signature(mg.GemmaRMSNorm.forward).parameters
        assert not hasattr(mg, "_gated_residual")
        print("untouched")
    """)
    assert out.strip() == "untouched"


def test_compat_layer_supplies_the_fork_semantics_on_stock_transformers() -> None:
    out = _run("""
        import torch
        from graftcache.backbones.pi05_compat import ensure_pi05_runtime, fork_present, installed
        assert not fork_present() and not installed()
        assert ensure_pi05_runtime() is True and ensure_pi05_runtime() is True and installed()
        from transformers.models.siglip import check
        assert check.check_whether_transformers_replace_is_installed_correctly()
        from transformers.models.gemma import modeling_gemma as mg
        torch.manual_seed(0)
        plain, ada = mg.GemmaRMSNorm(8), mg.GemmaRMSNorm(8, cond_dim=4)
        x, cond = torch.randn(2, 3, 8), torch.randn(2, 4)
        y, gate = plain(x)
        assert gate is None and torch.allclose(y, x / x.pow(2).mean(-1, keepdim=True).add(1e-6).sqrt())
        torch.nn.init.normal_(ada.dense.weight)
        y, gate = ada(x, cond)
        scale, shift, g = ada.dense(cond).unsqueeze(1).chunk(3, -1)
        assert torch.allclose(y, plain(x)[0] * (1 + scale) + shift, atol=1e-6) and torch.equal(gate, g)
        assert torch.equal(mg._gated_residual(x, x, gate), x + x * gate)
        assert torch.equal(mg._gated_residual(x, x, None), 2 * x)
        print("patched")
    """)
    assert out.strip() == "patched"


def test_pi05_runs_in_bfloat16() -> None:
    """lerobot keeps SigLIP's patch embedding and the norms in fp32 under bf16; the layer must cope."""
    adapter = tiny("pi05")
    adapter.policy.model.paligemma_with_expert.to_bfloat16_for_selected_params("bfloat16")
    batch = adapter.prepare(raw_images(adapter, 2))
    with torch.no_grad():
        tokens = adapter.native_tokens(raw_images(adapter, 2)["observation.images.image"])
        chunk = adapter.predict(batch)
    assert tokens.shape == (2, 16, adapter.lm_width) and torch.isfinite(chunk).all()
