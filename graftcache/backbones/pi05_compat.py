"""Run lerobot 0.4.4's pi0.5 on stock PyPI transformers (4.56-4.57).

lerobot's pi0.5 was written against a transformers git fork (openpi's `transformers_replace`, branch
`fix/lerobot_openpi`) that PyPI cannot deliver. `PI05Pytorch.__init__` refuses to run unless
`transformers.models.siglip.check` imports (modeling_pi05.py:576-584), and the model relies on
fork behaviour that stock Gemma lacks. This module supplies those semantics by patching the stock
classes in place, and ONLY when the fork is absent:

- `GemmaRMSNorm(dim, eps, cond_dim=None)`; `forward(x, cond=None) -> (y, gate)`. With `cond_dim` it
  is adaptive RMSNorm (adaRMS): dense(cond) -> (scale, shift, gate), y = norm(x)*(1+scale)+shift.
  pi0.5 conditions its action expert on the flow time this way.
- `modeling_gemma._gated_residual(x, y, gate) = x + y*gate` (x + y without a gate).
- Decoder layers and `GemmaModel.forward` accept and route `adarms_cond`; `GemmaModel` does NOT
  multiply its inputs by sqrt(hidden) (pi0.5 scales its language embeddings itself).
- Attention with a prefix cache and `use_cache=False` reads the cached prefix K/V without
  appending the suffix (every denoising step reuses the same prefix cache).
- `PaliGemmaModel.get_image_features` without the 1/sqrt(text width) division.
- SigLIP's encoder accepts the fp32 patch embeddings lerobot keeps when the rest runs in bf16.

The patches are global for the process (any stock Gemma built afterwards gets them); SmolVLA's
Llama text model is unaffected.
"""

from __future__ import annotations

import importlib.util
import sys
import types

import torch
from torch import nn

from graftcache.errors import BackboneError

FORK_MODULE = "transformers.models.siglip.check"
_OURS = "_graftcache_pi05_compat"  # marks the stand-in `check` module this layer registers
_SUPPORTED = ((4, 56), (4, 57))


def fork_present() -> bool:
    """True when the transformers fork lerobot's pi0.5 was written for is the one installed."""
    module = sys.modules.get(FORK_MODULE)
    if module is not None:
        return not getattr(module, _OURS, False)
    try:
        return importlib.util.find_spec(FORK_MODULE) is not None
    except ModuleNotFoundError:
        return False


def installed() -> bool:
    module = sys.modules.get(FORK_MODULE)
    return module is not None and getattr(module, _OURS, False)


def ensure_pi05_runtime() -> bool:
    """Make pi0.5 runnable. Returns True when the compat layer is active, False when the fork is."""
    if installed():
        return True
    if fork_present():
        return False
    import transformers

    version = tuple(int(x) for x in transformers.__version__.split(".")[:2])
    if version not in _SUPPORTED:
        raise BackboneError(
            f"pi0.5 needs the lerobot transformers fork or stock transformers 4.56-4.57; found {transformers.__version__}"
        )
    _patch_norm()
    _patch_attention()
    _patch_decoder_layer()
    _patch_gemma_model()
    _patch_paligemma_and_siglip()
    _register_check_module()
    return True


def _register_check_module() -> None:
    """The stand-in for the fork's guard module, registered last so a failed install is retried."""
    import transformers.models.siglip as siglip

    check = types.ModuleType(FORK_MODULE)
    check.check_whether_transformers_replace_is_installed_correctly = lambda: True
    setattr(check, _OURS, True)
    sys.modules[FORK_MODULE] = check
    siglip.check = check


def _cond_dim(config) -> int | None:
    if not getattr(config, "use_adarms", False):
        return None
    return getattr(config, "adarms_cond_dim", None) or config.hidden_size


def _patch_norm() -> None:
    from transformers.modeling_utils import PreTrainedModel
    from transformers.models.gemma import modeling_gemma as mg

    def __init__(self, dim: int, eps: float = 1e-6, cond_dim: int | None = None) -> None:
        nn.Module.__init__(self)
        self.eps, self.dim, self.cond_dim = eps, dim, cond_dim
        if cond_dim is None:
            self.weight = nn.Parameter(torch.zeros(dim))
            self.dense = None
        else:
            self.dense = nn.Linear(cond_dim, 3 * dim, bias=True)
            nn.init.zeros_(self.dense.weight)

    def forward(self, x: torch.Tensor, cond: torch.Tensor | None = None):
        dtype = x.dtype
        normed = x * torch.rsqrt(x.float().pow(2).mean(-1, keepdim=True) + self.eps)
        if self.dense is None:
            return (normed * (1.0 + self.weight.float())).to(dtype), None
        if cond is None:
            raise ValueError("adaptive GemmaRMSNorm needs `cond`")
        modulation = self.dense(cond)
        if x.ndim == 3:
            modulation = modulation.unsqueeze(1)
        scale, shift, gate = modulation.chunk(3, dim=-1)
        normed = normed * (1.0 + scale.float()) + shift.float()
        return normed.to(dtype), gate.to(dtype)

    def extra_repr(self) -> str:
        kind = f"adaptive, cond_dim={self.cond_dim}" if self.dense is not None else "plain"
        return f"dim={self.dim}, eps={self.eps}, {kind}"

    def gated_residual(x, y, gate):
        if x is None or y is None:
            return y if x is None else x
        return x + y if gate is None else x + y * gate

    def init_weights(self, module: nn.Module) -> None:
        PreTrainedModel._init_weights(self, module)
        if "RMSNorm" in type(module).__name__ and getattr(module, "weight", None) is not None:
            module.weight.data.zero_()

    mg.GemmaRMSNorm.__init__ = __init__
    mg.GemmaRMSNorm.forward = forward
    mg.GemmaRMSNorm.extra_repr = extra_repr
    mg._gated_residual = gated_residual
    mg.GemmaPreTrainedModel._init_weights = init_weights


def _patch_attention() -> None:
    from transformers.modeling_utils import ALL_ATTENTION_FUNCTIONS
    from transformers.models.gemma import modeling_gemma as mg

    def forward(self, hidden_states, position_embeddings, attention_mask, past_key_values=None,
                cache_position=None, use_cache: bool = False, **kwargs):
        kwargs.pop("position_ids", None)
        shape = (*hidden_states.shape[:-1], -1, self.head_dim)
        q = self.q_proj(hidden_states).view(shape).transpose(1, 2)
        k = self.k_proj(hidden_states).view(shape).transpose(1, 2)
        v = self.v_proj(hidden_states).view(shape).transpose(1, 2)
        cos, sin = position_embeddings
        q, k = mg.apply_rotary_pos_emb(q, k, cos, sin)
        if past_key_values is not None and use_cache:
            k, v = past_key_values.update(k, v, self.layer_idx,
                                          {"sin": sin, "cos": cos, "cache_position": cache_position})
        elif past_key_values is not None:  # read-only prefix: the suffix is not written back
            layer = past_key_values.layers[self.layer_idx]
            k = torch.cat([layer.keys, k], dim=2)
            v = torch.cat([layer.values, v], dim=2)
        attend = mg.eager_attention_forward
        if self.config._attn_implementation != "eager":
            attend = ALL_ATTENTION_FUNCTIONS[self.config._attn_implementation]
        out, weights = attend(self, q, k, v, attention_mask, scaling=self.scaling,
                              dropout=self.attention_dropout if self.training else 0.0, **kwargs)
        return self.o_proj(out.reshape(*hidden_states.shape[:-1], -1).contiguous()), weights

    mg.GemmaAttention.forward = forward


def _patch_decoder_layer() -> None:
    from transformers.models.gemma import modeling_gemma as mg

    stock_init = mg.GemmaDecoderLayer.__init__

    def __init__(self, config, layer_idx: int) -> None:
        stock_init(self, config, layer_idx)
        cond_dim = _cond_dim(config)
        if cond_dim is not None:
            self.input_layernorm = mg.GemmaRMSNorm(config.hidden_size, config.rms_norm_eps, cond_dim)
            self.post_attention_layernorm = mg.GemmaRMSNorm(config.hidden_size, config.rms_norm_eps, cond_dim)

    def forward(self, hidden_states, attention_mask=None, position_ids=None, past_key_values=None,
                use_cache=False, cache_position=None, position_embeddings=None, adarms_cond=None, **kwargs):
        h, gate = self.input_layernorm(hidden_states, adarms_cond)
        h, _ = self.self_attn(hidden_states=h, attention_mask=attention_mask, position_ids=position_ids,
                              past_key_values=past_key_values, use_cache=use_cache,
                              cache_position=cache_position, position_embeddings=position_embeddings, **kwargs)
        hidden_states = mg._gated_residual(hidden_states, h, gate)
        h, gate = self.post_attention_layernorm(hidden_states, adarms_cond)
        return mg._gated_residual(hidden_states, self.mlp(h), gate)

    mg.GemmaDecoderLayer.__init__ = __init__
    mg.GemmaDecoderLayer.forward = forward


def _patch_gemma_model() -> None:
    from transformers.cache_utils import DynamicCache
    from transformers.masking_utils import create_causal_mask
    from transformers.modeling_outputs import BaseModelOutputWithPast
    from transformers.models.gemma import modeling_gemma as mg

    stock_init = mg.GemmaModel.__init__

    def __init__(self, config) -> None:
        stock_init(self, config)
        cond_dim = _cond_dim(config)
        if cond_dim is not None:
            self.norm = mg.GemmaRMSNorm(config.hidden_size, config.rms_norm_eps, cond_dim)

    def forward(self, input_ids=None, attention_mask=None, position_ids=None, past_key_values=None,
                inputs_embeds=None, use_cache=None, cache_position=None, adarms_cond=None, **kwargs):
        if (input_ids is None) == (inputs_embeds is None):
            raise ValueError("pass exactly one of input_ids or inputs_embeds")
        use_cache = self.config.use_cache if use_cache is None else use_cache
        hidden = self.embed_tokens(input_ids) if inputs_embeds is None else inputs_embeds
        if use_cache and past_key_values is None:
            past_key_values = DynamicCache(config=self.config)
        if cache_position is None:
            seen = past_key_values.get_seq_length() if past_key_values is not None else 0
            cache_position = torch.arange(seen, seen + hidden.shape[1], device=hidden.device)
        if position_ids is None:
            position_ids = cache_position.unsqueeze(0)
        mask = create_causal_mask(config=self.config, input_embeds=hidden, attention_mask=attention_mask,
                                  cache_position=cache_position, past_key_values=past_key_values,
                                  position_ids=position_ids)
        if len(self.layers) and self.layers[0].self_attn.q_proj.weight.dtype == torch.bfloat16:
            hidden = hidden.to(torch.bfloat16)
        rotary = self.rotary_emb(hidden, position_ids)
        for layer in self.layers[: self.config.num_hidden_layers]:  # no `* sqrt(hidden_size)` first
            hidden = layer(hidden, attention_mask=mask, position_ids=position_ids, past_key_values=past_key_values,
                           use_cache=use_cache, cache_position=cache_position, position_embeddings=rotary,
                           adarms_cond=adarms_cond, **kwargs)
        hidden, _ = self.norm(hidden, adarms_cond)
        return BaseModelOutputWithPast(last_hidden_state=hidden, past_key_values=past_key_values if use_cache else None)

    mg.GemmaModel.__init__ = __init__
    mg.GemmaModel.forward = forward


def _patch_paligemma_and_siglip() -> None:
    from transformers.models.paligemma import modeling_paligemma as mp
    from transformers.models.siglip import modeling_siglip as ms

    def get_image_features(self, pixel_values: torch.Tensor) -> torch.Tensor:
        return self.multi_modal_projector(self.vision_tower(pixel_values).last_hidden_state)

    stock_encoder_forward = ms.SiglipEncoder.forward

    def encoder_forward(self, inputs_embeds, attention_mask=None, **kwargs):
        if len(self.layers) and self.layers[0].self_attn.q_proj.weight.dtype == torch.bfloat16:
            inputs_embeds = inputs_embeds.to(torch.bfloat16)
        return stock_encoder_forward(self, inputs_embeds, attention_mask, **kwargs)

    mp.PaliGemmaModel.get_image_features = get_image_features
    ms.SiglipEncoder.forward = encoder_forward
