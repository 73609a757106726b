"""Random-init SmolVLA and pi0.5 at the released geometry, written as lerobot 0.6 writes a released
policy and placed in a Hugging Face hub cache snapshot, so `--policy org/name` loads them offline
exactly as it would load real weights.

Why: no released weights can be downloaded here, and the tiny configurations cannot show what only
the real geometry has: SmolVLA's 64 tokens x 960 per camera scaled by sqrt(960) (SmolVLM2-500M),
pi0.5's 256 tokens x 2048 per camera, its hard-coded 8 heads x 1 KV head and 257152-token
vocabulary (PaliGemma gemma_2b + gemma_300m expert). Layout written (as the hub client writes it):

    <HF_HUB_CACHE>/models--ORG--NAME/{blobs/<sha256>, refs/main, snapshots/<rev>/<file> -> blob}

with the policy files `config.json`, `model.safetensors`, `policy_{pre,post}processor.json` and
their state files, plus the hub repos construction reads: SmolVLA's `vlm_model_name`
(HuggingFaceTB/SmolVLM2-500M-Video-Instruct: the real SmolVLM2-500M config, graftcache's tiny
tokenizer) and pi0.5's hard-coded tokenizer (google/paligemma-3b-pt-224: the tiny PaliGemma-style
tokenizer). Every policy folder carries graftcache.backbones.checkpoint.RANDOM_MARKER, whose reader
(`is_random_release`) is library code, so whatever graftcache records from it (cache manifests, results
rows, reports) says random_init. Run offline (HF_HUB_OFFLINE=1).

A developer tool, not library code: only tests and benchmarks build these checkpoints.
"""

from __future__ import annotations

import contextlib
import hashlib
import itertools
import json
import os
import shutil
import struct
import tempfile
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import nn

from graftcache.backbones.checkpoint import RANDOM_MARKER, follow_umask, quiet
from graftcache.backbones.tiny_assets import PALIGEMMA_DIR, SMOLVLM_DIR
from graftcache.hashing import sha256_file
from graftcache.hub_cache import hub_cache as default_hub_cache
from graftcache.hub_cache import repo_dir

SMOLVLM_REPO = "HuggingFaceTB/SmolVLM2-500M-Video-Instruct"  # SmolVLAConfig.vlm_model_name's default
PALIGEMMA_REPO = "google/paligemma-3b-pt-224"  # hard-coded by lerobot's pi0.5 processor
SAFETENSORS_DTYPES = {torch.float32: "F32", torch.bfloat16: "BF16", torch.float16: "F16"}
#: SmolVLM2-500M: SigLIP-B/16 at 512 px (32x32 patches x 768), pixel shuffle x4 -> 64 tokens, Llama 960 wide.
SMOLVLM2_500M = {
    "scale_factor": 4,
    "vision": {"hidden_size": 768, "intermediate_size": 3072, "num_hidden_layers": 12,
               "num_attention_heads": 12, "image_size": 512, "patch_size": 16},
    "text": {"model_type": "llama", "hidden_size": 960, "intermediate_size": 2560, "num_hidden_layers": 32,
             "num_attention_heads": 15, "num_key_value_heads": 5, "head_dim": 64, "vocab_size": 49280,
             "max_position_embeddings": 8192, "rope_theta": 100000.0, "rms_norm_eps": 1e-5},
}


@dataclass(frozen=True)
class Recipe:
    """The dataset side of a released policy. Default: LIBERO (two 256 px cameras, state 8, action 7,
    chunk 50 as lerobot's defaults for both policies)."""

    cameras: tuple[str, ...] = ("image", "image2")
    image_size: int = 256
    state_dim: int = 8
    action_dim: int = 7
    chunk_size: int = 50
    pi05_empty_cameras: int = 1   # pi0.5's LIBERO recipe: a third, always-masked image slot
    seed: int = 0


LIBERO = Recipe()


def versions() -> dict[str, str]:
    """The libraries a checkpoint's key names and files depend on (transformers renames modules between
    releases: a pi0.5 written under 5.17 does not load under 5.5)."""
    import importlib.metadata

    return {name: importlib.metadata.version(name) for name in ("lerobot", "transformers", "torch")}


def built_here(folder: Path) -> bool:
    """Whether `folder` is a random release written with this environment's `versions()` (safe to reuse)."""
    try:
        return json.loads((folder / RANDOM_MARKER).read_text()).get("versions") == versions()
    except (OSError, ValueError):
        return False


def unit_stats(recipe: Recipe = LIBERO) -> dict:
    """lerobot-format stats with every field MEAN_STD and QUANTILES read: identity normalisation."""
    def fields(n: int) -> dict[str, torch.Tensor]:
        one, zero = torch.ones(n), torch.zeros(n)
        return {"mean": zero, "std": one, "min": -one, "max": one, "q01": -one, "q99": one}

    return {"observation.state": fields(recipe.state_dim), "action": fields(recipe.action_dim)}


@contextlib.contextmanager
def hub_cache(cache: Path) -> Iterator[None]:
    """Make transformers and lerobot resolve hub ids in `cache` (huggingface_hub reads HF_HUB_CACHE only
    at import; graftcache's own lookups read the environment at call time)."""
    from huggingface_hub import constants

    saved = (os.environ.get("HF_HUB_CACHE"), constants.HF_HUB_CACHE)
    os.environ["HF_HUB_CACHE"] = constants.HF_HUB_CACHE = str(cache)
    try:
        yield
    finally:
        constants.HF_HUB_CACHE = saved[1]
        if saved[0] is None:
            os.environ.pop("HF_HUB_CACHE")
        else:
            os.environ["HF_HUB_CACHE"] = saved[0]


# ---------------------------------------------------------------------------------------------- hub layout
def publish(staging: Path, repo_id: str, cache: Path) -> Path:
    """Move the files of `staging` into the hub cache as the snapshot `refs/main` points to; returns it.
    The revision is a hash of the contents, so rebuilding identical files gives the same snapshot."""
    repo = repo_dir(repo_id, cache=cache)
    files = sorted(p for p in staging.rglob("*") if p.is_file())
    blobs = {p: sha256_file(p) for p in files}
    listing = "".join(f"{p.relative_to(staging)}:{h};" for p, h in blobs.items())
    revision = hashlib.sha1(listing.encode()).hexdigest()
    snapshot = repo / "snapshots" / revision
    shutil.rmtree(snapshot, ignore_errors=True)
    (repo / "blobs").mkdir(parents=True, exist_ok=True)
    for path, digest in blobs.items():
        blob = repo / "blobs" / digest
        path.replace(blob)
        link = snapshot / path.relative_to(staging)
        link.parent.mkdir(parents=True, exist_ok=True)
        link.symlink_to(os.path.relpath(blob, link.parent))
    (repo / "refs").mkdir(exist_ok=True)
    (repo / "refs" / "main").write_text(revision)
    return snapshot


@contextlib.contextmanager
def _staging(cache: Path) -> Iterator[Path]:
    """A scratch folder on the cache's file system, so publishing renames instead of copying gigabytes."""
    cache.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix=".graftcache-staging-", dir=cache) as tmp:
        yield Path(tmp)


def write_smolvlm2(cache: Path) -> Path:
    """SmolVLA's `vlm_model_name` repo: the SmolVLM2-500M config (what construction reads for the
    geometry) and a processor around graftcache's tiny tokenizer (SmolVLA uses only its image token ids)."""
    from transformers import AutoTokenizer, SmolVLMConfig
    from transformers.models.smolvlm import SmolVLMImageProcessor, SmolVLMProcessor
    from transformers.models.smolvlm.video_processing_smolvlm import SmolVLMVideoProcessor

    g = SMOLVLM2_500M
    tok = AutoTokenizer.from_pretrained(SMOLVLM_DIR)
    vision = g["vision"]
    tokens = (vision["image_size"] // vision["patch_size"]) ** 2 // g["scale_factor"] ** 2
    with _staging(cache) as out:
        SmolVLMConfig(image_token_id=tok.convert_tokens_to_ids("<image>"), scale_factor=g["scale_factor"],
                      pad_token_id=tok.pad_token_id, tie_word_embeddings=False, vision_config=dict(vision),
                      text_config={**g["text"], "pad_token_id": tok.pad_token_id}).save_pretrained(out)
        SmolVLMProcessor(
            image_processor=SmolVLMImageProcessor(size={"longest_edge": 4 * vision["image_size"]},
                                                  max_image_size={"longest_edge": vision["image_size"]}),
            tokenizer=tok, video_processor=SmolVLMVideoProcessor(), image_seq_len=tokens,
        ).save_pretrained(out)
        return publish(out, SMOLVLM_REPO, cache)


def write_paligemma_tokenizer(cache: Path) -> Path:
    """pi0.5's tokenizer repo: graftcache's tiny PaliGemma-style tokenizer (ids < 257152) and PaliGemma's
    default config (AutoTokenizer reads the config of a hub id)."""
    from transformers import PaliGemmaConfig

    with _staging(cache) as out:
        PaliGemmaConfig().save_pretrained(out)
        for f in PALIGEMMA_DIR.iterdir():
            shutil.copy2(f, out / f.name)
        return publish(out, PALIGEMMA_REPO, cache)


def _construct_on_meta(policy_cls, config, dtype: torch.dtype = torch.float32):
    """lerobot's own constructor on the meta device: the architecture, names, shapes and dtypes of
    every tensor, and no memory (a materialised pi0.5 is 9.4 GB even in bf16: its vision path, norms and
    adaRMS projections stay fp32, and both Gemmas keep a 257152-row lm_head)."""
    device, config.device = config.device, "meta"  # the policies move themselves to config.device
    saved = torch.get_default_dtype()
    torch.set_default_dtype(dtype)
    try:
        with torch.device("meta"):
            return policy_cls(config)
    finally:
        torch.set_default_dtype(saved)
        config.device = device


def _init_module(module: nn.Module, owner) -> None:
    """Initialise a materialised module's own tensors as its model would: transformers' `_init_weights`
    inside a transformers model, else the module's `reset_parameters` (torch's defaults)."""
    for param in module.parameters(recurse=False):
        nn.init.zeros_(param)
    if owner is not None:
        owner._init_weights(module)
    elif hasattr(module, "reset_parameters"):
        module.reset_parameters()


@torch.no_grad()
def write_random_weights(policy: nn.Module, path: Path, seed: int) -> None:
    """`model.safetensors` as lerobot's `save_pretrained` writes it (safetensors `save_model`: every
    state-dict tensor once, widest dtype first so each stays aligned, metadata format=pt) for a policy on
    the meta device: module by module, materialised in fp32 (torch's random init is 3x slower in bf16 on
    CPUs), seeded-initialised (`_init_module`), cast to its dtype, written and put back on the meta device,
    so memory peaks at the largest module (pi0.5's 257152 x 2048 embedding), not at the policy. The global
    RNG is left as it was."""
    state = policy.state_dict(keep_vars=True)
    modules = dict(policy.named_modules())
    owner = _hf_owner(policy)
    sizes = sorted({t.element_size() for t in state.values()}, reverse=True)
    order = [name for size in sizes for name, t in state.items() if t.element_size() == size]
    header: dict = {"__metadata__": {"format": "pt"}}
    offset = 0
    for name in order:
        t = state[name]
        nbytes = t.numel() * t.element_size()
        header[name] = {"dtype": SAFETENSORS_DTYPES[t.dtype], "shape": list(t.shape),
                        "data_offsets": [offset, offset + nbytes]}
        offset += nbytes
    blob = json.dumps(header, separators=(",", ":")).encode()
    blob += b" " * (-len(blob) % 8)
    with torch.random.fork_rng(devices=[]), path.open("wb") as f:
        torch.manual_seed(seed)
        f.write(struct.pack("<Q", len(blob)) + blob)
        for module_name, names in itertools.groupby(order, key=lambda name: name.rpartition(".")[0]):
            module = modules[module_name]
            meta = dict(module.named_parameters(recurse=False))
            for local, param in meta.items():
                setattr(module, local, nn.Parameter(torch.empty(param.shape, dtype=torch.float32)))
            _init_module(module, owner(module_name))
            for name in names:
                local = name.rpartition(".")[2]
                tensor = getattr(module, local).detach().to(meta[local].dtype)
                f.write(memoryview(tensor.view(torch.uint8).numpy()))
            for local, param in meta.items():
                setattr(module, local, param)


def _publish_policy(policy, pre, post, repo_id: str, cache: Path, recipe: Recipe) -> Path:
    """Write a meta-device policy as lerobot writes a released one (config, weights, processors), mark it
    random-init and publish it."""
    with _staging(cache) as out:
        policy.config._save_pretrained(out)
        write_random_weights(policy, out / "model.safetensors", recipe.seed)
        pre.save_pretrained(out)
        post.save_pretrained(out)
        marker = {"random_init": True, "seed": recipe.seed, "built_by": __name__, "versions": versions(),
                  "note": "random weights at the released geometry, not a released policy"}
        (out / RANDOM_MARKER).write_text(json.dumps(marker, indent=1))
        follow_umask(out)
        return publish(out, repo_id, cache)


def _features(recipe: Recipe) -> tuple[dict, dict]:
    from lerobot.configs.types import FeatureType, PolicyFeature

    shape = (3, recipe.image_size, recipe.image_size)
    inputs = {f"observation.images.{c}": PolicyFeature(FeatureType.VISUAL, shape) for c in recipe.cameras}
    inputs["observation.state"] = PolicyFeature(FeatureType.STATE, (recipe.state_dim,))
    return inputs, {"action": PolicyFeature(FeatureType.ACTION, (recipe.action_dim,))}


# ---------------------------------------------------------------------------------------------- policies
def smolvla_config(cache: Path, recipe: Recipe = LIBERO):
    """lerobot's SmolVLA config at the released geometry (SmolVLM2-500M, first 16 LM layers, expert 0.75 wide;
    lerobot's defaults) for `recipe`'s dataset side, with the hub repo its construction reads written to `cache`."""
    from lerobot.policies.smolvla.configuration_smolvla import SmolVLAConfig

    inputs, outputs = _features(recipe)
    write_smolvlm2(cache)
    return SmolVLAConfig(vlm_model_name=SMOLVLM_REPO, load_vlm_weights=False, chunk_size=recipe.chunk_size,
                         n_action_steps=recipe.chunk_size, device="cpu", input_features=inputs,
                         output_features=outputs)


def _mean_std() -> dict:
    """The LIBERO recipe's normalisation of the PaliGemma policies (pi0, pi0.5)."""
    from lerobot.configs.types import NormalizationMode

    return {"VISUAL": NormalizationMode.IDENTITY, "STATE": NormalizationMode.MEAN_STD,
            "ACTION": NormalizationMode.MEAN_STD}


def pi05_config(cache: Path, recipe: Recipe = LIBERO, dtype: str = "bfloat16"):
    """lerobot's pi0.5 config at the released geometry (PaliGemma gemma_2b + gemma_300m expert, SigLIP So400m/14
    at 224 px) for `recipe`, with the tokenizer repo its processors read written to `cache`. `dtype` is
    `PI05Config.dtype` ("bfloat16": LM and expert bf16, vision path, norms and adaRMS projections fp32)."""
    from lerobot.policies.pi05.configuration_pi05 import PI05Config

    inputs, outputs = _features(recipe)
    write_paligemma_tokenizer(cache)
    return PI05Config(dtype=dtype, chunk_size=recipe.chunk_size, n_action_steps=recipe.chunk_size,
                      empty_cameras=recipe.pi05_empty_cameras, normalization_mapping=_mean_std(), device="cpu",
                      input_features=inputs, output_features=outputs)


def pi0_config(cache: Path, recipe: Recipe = LIBERO, dtype: str = "bfloat16"):
    """lerobot's pi0 config at the released geometry (PaliGemma gemma_2b + gemma_300m expert, a masked third
    camera slot as pi0.5's LIBERO recipe), with the tokenizer repo its processors read written to `cache`."""
    from lerobot.policies.pi0.configuration_pi0 import PI0Config

    inputs, outputs = _features(recipe)
    write_paligemma_tokenizer(cache)
    return PI0Config(dtype=dtype, chunk_size=recipe.chunk_size, n_action_steps=recipe.chunk_size,
                     empty_cameras=recipe.pi05_empty_cameras, normalization_mapping=_mean_std(), device="cpu",
                     input_features=inputs, output_features=outputs)


#: Backbones whose released geometry this module can build: name -> its config builder.
CONFIGS = {"smolvla": smolvla_config, "pi05": pi05_config, "pi0": pi0_config}


def build_smolvla(repo_id: str, *, cache: Path | None = None, recipe: Recipe = LIBERO,
                  stats: dict | None = None) -> Path:
    """Random-init SmolVLA (smolvla_config) published as `repo_id`; returns its snapshot folder. fp32, ~450M
    parameters."""
    from lerobot.policies.smolvla.modeling_smolvla import SmolVLAPolicy
    from lerobot.policies.smolvla.processor_smolvla import make_smolvla_pre_post_processors

    cache = Path(cache or default_hub_cache())
    with hub_cache(cache), quiet():
        config = smolvla_config(cache, recipe)
        policy = _construct_on_meta(SmolVLAPolicy, config)
        pre, post = make_smolvla_pre_post_processors(config, dataset_stats=stats or unit_stats(recipe))
        return _publish_policy(policy, pre, post, repo_id, cache, recipe)


def build_pi05(repo_id: str, *, cache: Path | None = None, recipe: Recipe = LIBERO, stats: dict | None = None,
               dtype: str = "bfloat16") -> Path:
    """Random-init pi0.5 (pi05_config) published as `repo_id`; returns its snapshot folder. bf16: 9.4 GB;
    "float32": 16.6 GB; 4.1B parameters, both Gemmas' 257152-row lm_heads included. Building takes ~5 GB of
    memory whatever the dtype (`write_random_weights`)."""
    from lerobot.policies.pi05.modeling_pi05 import PI05Policy
    from lerobot.policies.pi05.processor_pi05 import make_pi05_pre_post_processors

    cache = Path(cache or default_hub_cache())
    with hub_cache(cache), quiet():
        config = pi05_config(cache, recipe, dtype)
        policy = _construct_on_meta(PI05Policy, config, getattr(torch, dtype))
        pre, post = make_pi05_pre_post_processors(config, dataset_stats=stats or unit_stats(recipe))
        return _publish_policy(policy, pre, post, repo_id, cache, recipe)


# ---------------------------------------------------------------------------------------------- on a device
def _hf_owner(policy: nn.Module) -> Callable[[str], nn.Module | None]:
    """module name -> the innermost transformers model holding it (whose `_init_weights` initialises it)."""
    from transformers import PreTrainedModel

    modules = dict(policy.named_modules())
    hf_models = [name for name, m in modules.items() if isinstance(m, PreTrainedModel)]

    def owner(name: str) -> nn.Module | None:
        prefixes = [p for p in hf_models if name == p or name.startswith(p + ".")]
        return modules[max(prefixes, key=len)] if prefixes else None

    return owner


@torch.no_grad()
def materialise(policy: nn.Module, device: torch.device, seed: int = 0) -> None:
    """Create every meta parameter of `policy` on `device` and initialise it as its model would (`_init_module`,
    module by module, in fp32, then cast to the parameter's own dtype), and move every buffer there: random
    weights at any size with no host copy and nothing written. Tied parameters stay one object. The global RNG
    (CPU and `device`'s) is left as it was."""
    owner = _hf_owner(policy)
    made: dict[int, nn.Parameter] = {}
    devices = [device] if device.type == "cuda" else []
    with torch.random.fork_rng(devices=devices):
        torch.manual_seed(seed)
        for name, module in policy.named_modules():
            meta = {local: p for local, p in module.named_parameters(recurse=False) if p.is_meta}
            if not meta:
                continue
            fresh = {local: id(p) not in made for local, p in meta.items()}
            for local, p in meta.items():
                setattr(module, local, made.get(id(p)) or nn.Parameter(
                    torch.empty(p.shape, dtype=torch.float32, device=device), requires_grad=p.requires_grad))
            if any(fresh.values()):
                _init_module(module, owner(name))
            for local, p in meta.items():
                if fresh[local]:
                    made[id(p)] = nn.Parameter(getattr(module, local).detach().to(p.dtype),
                                               requires_grad=p.requires_grad)
                setattr(module, local, made[id(p)])
    for module in policy.modules():
        for local, buffer in module._buffers.items():
            if buffer is not None and buffer.device != device:
                module._buffers[local] = buffer.to(device)


def on_device(name: str, device: str | torch.device, *, cache: Path, recipe: Recipe = LIBERO, seed: int = 0):
    """Backbone `name` at the released geometry, random-init, built straight on `device` (lerobot's constructor
    with its parameters on the meta device, then `materialise`): the graftcache adapter with the policy's own
    processors over identity stats. Its `source` says what it is; `random_init` is True."""
    from graftcache.backbones import get_backbone

    if name not in CONFIGS:
        raise ValueError(f"no released-geometry config for {name!r} (devtools.released knows {', '.join(CONFIGS)})")
    device = torch.device(device)
    cache = Path(cache)
    with hub_cache(cache), quiet():
        return built_on(get_backbone(name), CONFIGS[name](cache, recipe), device, unit_stats(recipe),
                        source=f"{name} released geometry, random init on {device}", seed=seed)


def built_on(adapter_cls, config, device: torch.device, stats: dict, *, source: str, marker: dict | None = None,
             seed: int = 0):
    """The adapter of a random-init policy of `config` built on `device`: lerobot's constructor (at a tiny
    `marker`'s sizes where given) with its parameters on the meta device, `materialise`, and the policy's own
    processors over `stats`."""
    from graftcache.backbones.lean_load import construct

    config.device = str(device)
    policy = construct(lambda: adapter_cls._construct(config, marker), config)
    materialise(policy, device, seed)
    policy.eval()
    pre, post = adapter_cls._make_processors(policy.config, stats, marker)
    return adapter_cls(policy, pre, post, source=source, random_init=True, tiny_marker=marker)


BUILDERS = {"smolvla": build_smolvla, "pi05": build_pi05}
