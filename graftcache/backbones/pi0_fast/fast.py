"""pi0-FAST's FAST action tokenizer, read without remote code, and pi0-FAST's construction and processors around it.

Released checkpoints name a hub processor (`action_tokenizer_name`) that lerobot loads as remote code; here it is read
from a folder with the FAST processor lerobot 0.6.1 ships (policies/molmoact2/molmoact2_hf_model/action_tokenizer.py),
and handed to PI0FastPolicy's constructor and to lerobot's processor factory in place of their own loads by name.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from pathlib import Path
from types import SimpleNamespace

from graftcache.backbones.patching import patched
from graftcache.errors import BackboneError

MODELING = "lerobot.policies.pi0_fast.modeling_pi0_fast"
FAST_DIR = "fast_tokenizer"  # a checkpoint's own FAST tokenizer, beside its weights


def load_fast(path: Path):
    """A saved FAST processor folder (tokenizer files + processor_config.json) as lerobot's FAST processor."""
    from lerobot.policies.molmoact2.molmoact2_hf_model.action_tokenizer import UniversalActionProcessor

    if not (path / "tokenizer.json").is_file():
        raise BackboneError(f"{path}: not a FAST action tokenizer (no tokenizer.json)")
    return UniversalActionProcessor.from_pretrained_local(str(path))

@contextlib.contextmanager
def policy_tokenizers(fast, text: Path) -> Iterator[None]:
    """PI0FastPolicy's constructor loads the FAST processor as remote code and the PaliGemma tokenizer by name
    (modeling_pi0_fast.py:768): hand it these instead."""
    import importlib

    from transformers import AutoTokenizer

    module = importlib.import_module(MODELING)
    def text_tokenizer(_, **kw):
        return AutoTokenizer.from_pretrained(text, **kw)

    with patched(module, AutoProcessor=SimpleNamespace(from_pretrained=lambda *_, **__: fast),
                 AutoTokenizer=SimpleNamespace(from_pretrained=text_tokenizer)):
        yield

def fast_processors(config, stats: dict, fast):
    """lerobot's pi0-FAST processors with the given FAST processor and the PaliGemma tokenizer folder the config
    names (the factory loads both by name, processor_pi0_fast.py:134-150)."""
    import functools

    import lerobot.policies.pi0_fast.processor_pi0_fast as pf
    from lerobot.processor import ActionTokenizerProcessorStep, TokenizerProcessorStep
    from transformers import AutoTokenizer

    text = AutoTokenizer.from_pretrained(config.text_tokenizer_name)
    with patched(pf, TokenizerProcessorStep=functools.partial(TokenizerProcessorStep, tokenizer=text),
                 ActionTokenizerProcessorStep=functools.partial(ActionTokenizerProcessorStep,
                                                                action_tokenizer_input_object=fast)):
        return pf.make_pi0_fast_pre_post_processors(config, dataset_stats=stats)
