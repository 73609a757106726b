"""pi0-FAST (lerobot 0.6, PaliGemma gemma_2b, FAST action tokens, no action expert) as a graftable backbone.

Vision path (modeling_pi0_fast.py:171, 964): as pi0's. SigLIP So400m/14 at 224 px -> multi_modal_projector
Linear(1152 -> 2048) = 256 tokens x 2048 per camera (lerobot divides and multiplies them by sqrt(2048): no
scaling). The graft replaces SigLIP with a pass-through and the projector with the graft projector.

There is no flow model. The action chunk (normalised) is a sequence of FAST tokens (DCT per action dimension,
quantised, BPE-compressed; lerobot's ActionTokenizerProcessorStep) that PaliGemma predicts autoregressively
after the images and the prompt ("Task: ..., State: <256-bin state>;\\n"). So, for this backbone:
- the training loss is lerobot's own: cross-entropy on the FAST tokens, one token-weighted mean over the batch
  (`PI0FastPytorch.forward`), returned as it is (a scalar; callers take its mean);
- "offline action MSE" scores the chunk lerobot's own `predict_action_chunk` decodes: greedy (temperature 0,
  so deterministic; flow noise and denoising steps do not apply and are ignored), FAST tokens -> DCT
  coefficients -> inverse DCT, with lerobot's relaxed decoding (a malformed sequence is padded or cut to the
  chunk, or decodes to zeros) and without the "Action:" prefix assertion, so an ill-formed graft's tokens
  score as what they decode to instead of aborting the cell.

The FAST tokenizer: released checkpoints name a hub processor (`action_tokenizer_name`, lerobot's default
`lerobot/fast-action-tokenizer`, openpi's `physical-intelligence/fast`) that lerobot loads as remote code. Here
it is read from the local HF cache (or a checkpoint's own `fast_tokenizer/` folder) with the FAST processor
lerobot 0.6.1 ships (policies/molmoact2/molmoact2_hf_model/action_tokenizer.py, the same algorithm without
remote code); absent, loading is refused in one line naming the repo. Tiny policies train their own with that
processor's `fit` (the FAST recipe: BPE on the quantised DCT coefficients), saved beside their weights.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import torch
from torch import nn

from graftcache.backbones.base import vlm_folder
from graftcache.backbones.batches import TOKEN_MASK, TOKENS
from graftcache.backbones.checkpoint import local_or_cached
from graftcache.backbones.paligemma import pi05_tiny_sizes
from graftcache.backbones.patching import patched
from graftcache.backbones.pi0_fast.fast import FAST_DIR, MODELING, fast_processors, load_fast, policy_tokenizers
from graftcache.backbones.pi0_fast.spec import SPEC
from graftcache.backbones.pi05.adapter import PaliGemmaAdapter
from graftcache.backbones.policy_loss import TokenLoss
from graftcache.backbones.tiny_assets import PALIGEMMA_DIR

ACTION_TOKENS = "action.tokens"  # lerobot.utils.constants.ACTION_TOKENS / ACTION_TOKEN_MASK
ACTION_TOKEN_MASK = "action.token_mask"


class PI0FastAdapter(TokenLoss, PaliGemmaAdapter):
    name = "pi0_fast"
    spec = SPEC

    # ------------------------------------------------------------------------------ construction
    @classmethod
    def _construct(cls, config, marker: dict | None) -> nn.Module:
        from lerobot.policies.pi0_fast.modeling_pi0_fast import PI0FastPolicy

        fast, text = Path(config.action_tokenizer_name), Path(config.text_tokenizer_name)  # set by _configure
        sizes = pi05_tiny_sizes(marker["geometry"], MODELING) if marker is not None else contextlib.nullcontext()
        with sizes, policy_tokenizers(load_fast(fast), text):
            return PI0FastPolicy(config)

    @classmethod
    def _configure(cls, folder: Path, config, marker: dict | None) -> None:
        fast, text = cls._tokenizer_folders(folder, config, marker)
        config.action_tokenizer_name, config.text_tokenizer_name = str(fast), str(text)  # read by the processors

    @classmethod
    def _tokenizer_folders(cls, folder: Path, config, marker: dict | None) -> tuple[Path, Path]:
        """(FAST processor folder, PaliGemma tokenizer folder): the checkpoint's own FAST tokenizer, else the
        one its config names (a folder or a hub id in the local HF cache); the shipped tiny PaliGemma tokenizer
        for tiny policies, else the config's (lerobot's default: google/paligemma-3b-pt-224)."""
        own = folder / FAST_DIR
        what = "pi0-FAST's FAST action tokenizer"
        fast = own if own.is_dir() else local_or_cached(config.action_tokenizer_name, what)
        text = vlm_folder(config.text_tokenizer_name, marker, PALIGEMMA_DIR, "pi0-FAST's tokenizer")
        return fast, text

    @classmethod
    def _processor_overrides(cls, config, marker: dict | None, device: str) -> tuple[dict, dict]:
        """The saved processors name neither tokenizer object, nor the PaliGemma tokenizer or `fast_skip_tokens`
        of the action step (lerobot's ActionTokenizerProcessorStep.get_config): given here from the config."""
        from transformers import AutoTokenizer

        pre, post = super(PaliGemmaAdapter, cls)._processor_overrides(config, marker, device)  # not PaliGemma's
        pre["tokenizer_processor"] = {"tokenizer": AutoTokenizer.from_pretrained(config.text_tokenizer_name)}
        pre["action_tokenizer_processor"] = {
            "action_tokenizer_input_object": load_fast(Path(config.action_tokenizer_name)),
            "paligemma_tokenizer_name": config.text_tokenizer_name, "fast_skip_tokens": config.fast_skip_tokens}
        return pre, post

    @classmethod
    def _make_processors(cls, config, stats: dict, marker: dict | None):
        return fast_processors(config, stats, load_fast(Path(config.action_tokenizer_name)))

    def save(self, folder: str | Path) -> Path:
        """The lerobot checkpoint plus its FAST tokenizer (`fast_tokenizer/`), which loading prefers."""
        folder = super().save(folder)
        self.policy.action_tokenizer.save_pretrained(folder / FAST_DIR)
        return folder

    # ----------------------------------------------------------------------------- policy loss
    def loss(self, batch: Mapping[str, Any], noise: torch.Tensor | None = None,
             time: torch.Tensor | None = None) -> torch.Tensor:
        """lerobot's pi0-FAST loss: cross-entropy on the FAST tokens of the chunk, one token-weighted mean over
        the batch (a scalar). `noise` and `time` are flow-matching inputs this backbone has none of."""
        policy = self.policy
        images, img_masks = policy._preprocess_images(batch)
        return policy.model.forward(images, img_masks, batch[TOKENS], batch[TOKEN_MASK], batch[ACTION_TOKENS],
                                    batch[ACTION_TOKEN_MASK])["loss"]

    def _predict_chunk(self, batch: Mapping[str, Any], noise: torch.Tensor, num_steps: int) -> torch.Tensor:
        with _greedy_chunks(self.config, self.chunk_size):
            return self.policy.predict_action_chunk(dict(batch)).to(self.device)

    def _switch_recompute(self, on: bool) -> None:
        """lerobot's switch minus the vision tower's (after a graft a pass-through, without transformers' method):
        transformers' own activation checkpointing of every language-model layer, non-reentrant."""
        model = self.policy.model
        language_model = model.paligemma_with_expert.paligemma.model.language_model
        model.gradient_checkpointing_enabled = on
        if on:
            language_model.gradient_checkpointing_enable(gradient_checkpointing_kwargs={"use_reentrant": False})
        else:
            language_model.gradient_checkpointing_disable()



@contextlib.contextmanager
def _greedy_chunks(config, chunk: int) -> Iterator[None]:
    """Greedy decoding of whole chunks for scoring: temperature 0, decoded over the chunk the tokens encode
    (lerobot decodes `n_action_steps`), no prefix assertion (see the module docstring)."""
    fields = {"temperature": 0.0, "n_action_steps": chunk, "validate_action_token_prefix": False}
    with patched(config, **fields):
        yield
