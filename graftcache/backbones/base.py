"""The backbone interface: one lerobot VLA policy, frozen, with the graft surgery and its policy loss.

An adapter wraps lerobot's own policy object and its own pre/post processors (normalisation stats
included); it re-implements no model code. It adds what graftcache needs around them, one job per
module: loading, geometry and the native tower here; `graft`/`reset`/`add_lora` in surgery.py;
`prepare`/`task_tokens` in batches.py; `loss`/`predict` in policy_loss.py:

- `load(source)`: "tiny", a hub id from the local HF cache, or a local checkpoint folder;
- `graft(projector)`: vision tower -> pass-through, connector -> projector, everything else frozen;
- `prepare(raw)`: a raw batch (cached features or pixels, raw state/action, task strings) through
  lerobot's preprocessor, with task strings tokenised once per task where the prompt allows it;
- `loss(batch)`: per-sample flow-matching loss with padded action steps masked (lerobot's policies
  return the unreduced per-element loss from `model.forward`, so the masking is done here, once, the
  same way for both backbones);
- `predict(batch, noise)`: the normalised action chunk, deterministic for fixed noise;
- `native_patch_grid` / `native_tokens`: the native tower's outputs for the native controls.

Batches (after `prepare`) are lerobot batches with cached features under `observation.vis_feats.<camera>`
([B, T, enc_dim]) in place of `observation.images.<camera>`.
"""

from __future__ import annotations

import functools
import operator
from abc import ABC, abstractmethod
from collections.abc import Iterable, Mapping
from importlib import import_module
from pathlib import Path
from typing import Any, ClassVar, Self

import torch
from torch import nn

from graftcache.backbone_registry import backbone_module
from graftcache.backbones.activation_checkpointing import ActivationCheckpointing
from graftcache.backbones.attention import Attention
from graftcache.backbones.batches import ACTION, STATE, PromptBatches
from graftcache.backbones.checkpoint import (
    PREPROCESSOR_FILE,
    follow_umask,
    is_random_release,
    load_processors,
    local_or_cached,
    quiet,
    resolve_source,
    state_dict_sha256,
    weights_file,
)
from graftcache.backbones.lean_load import construct, load_checkpoint, read_header
from graftcache.backbones.policy_loss import PolicyLoss
from graftcache.backbones.spec import BackboneSpec
from graftcache.backbones.surgery import GraftSurgery
from graftcache.backbones.tiny import TinyBuild, read_marker, write_marker
from graftcache.errors import BackboneError

#: Switches of lerobot's policy configs that change how a policy computes behind graftcache's back, and the value
#: `load` sets each to (where the config has the field) before the policy is built, tiny or from a checkpoint whose
#: config sets them, as public fine-tunes do: torch.compile of forward and sample_actions (SmolVLA, pi0, pi0.5,
#: pi0-FAST; every graft and reset would recompile), lerobot's own gradient checkpointing (pi0, pi0.5, pi0-FAST,
#: EO-1; EVO1's `enable_gradient_checkpointing`), which rows would record as `activation_checkpointing = off`, and
#: EVO1's bf16 autocast on CUDA (`use_amp`), under rows that say fp32. Recomputing is graftcache's switch
#: (`set_recompute_plan`), compiling its `fit --compile` (graftcache/backbones/compiled.py: the training forward,
#: after the graft), precision its autocast (--compute-dtype); GR00T's `use_bf16`, which decides
#: either way, follows the caller's autocast (graftcache.backbones.groot.adapter).
NEUTRAL_CONFIG: dict[str, Any] = {"compile_model": False, "gradient_checkpointing": False,
                                  "enable_gradient_checkpointing": False, "use_amp": False}


def neutralise(config) -> None:
    """Set `config`'s NEUTRAL_CONFIG switches to their neutral values."""
    for field, value in NEUTRAL_CONFIG.items():
        if hasattr(config, field):
            setattr(config, field, value)


def is_empty_camera(key: str) -> bool:
    """lerobot's placeholder camera slots (`empty_cameras`): masked out, never fed real images."""
    return key.rsplit(".", 1)[-1].startswith("empty_camera_")


def vlm_folder(name: str, marker: dict | None, shipped: Path, what: str) -> Path:
    """The folder of the VLM files (config, processor, tokenizer) a policy is built from beside its checkpoint, named
    by its config (`name`): for a tiny policy (`marker`) the shipped tiny folder, whatever its saved config names,
    since that path points into the package that saved it (another install, or a moved checkout); else a local
    folder or the hub id's snapshot in the local HF cache (graftcache.backbones.checkpoint.local_or_cached)."""
    if marker is not None:
        return shipped
    return local_or_cached(name, what)


def _camera_names(keys: Iterable[str]) -> tuple[str, ...]:
    return tuple(k.removeprefix("observation.images.") for k in keys)


class BackboneAdapter(GraftSurgery, PromptBatches, PolicyLoss, ActivationCheckpointing, Attention, ABC):
    """A frozen lerobot VLA policy that a projector can be grafted onto: its registry `name`, its constants as data
    (`spec`), and hooks where its behaviour differs."""

    name: ClassVar[str]
    spec: ClassVar[BackboneSpec]

    def __init_subclass__(cls, **kwargs: Any) -> None:
        """A class naming itself a backbone (`name` in its own body) is a registry entry, checked as it is defined
        (as lerobot's PreTrainedPolicy checks `name` and `config_class`): it lives in its folder's adapter.py,
        `graftcache.backbones.<name>.adapter` (graftcache.backbone_registry), and its `spec` is its folder's SPEC
        (`graftcache.backbones.<name>.spec`, which reports read without importing the adapter)."""
        super().__init_subclass__(**kwargs)
        if "name" not in cls.__dict__:
            return
        where = backbone_module(cls.name)
        if cls.__module__ != where:
            raise BackboneError(f"{cls.__qualname__} (in {cls.__module__}) names itself backbone {cls.name!r}: a "
                                f"backbone's adapter class is defined in {where} (its folder's adapter.py)")
        # its own, the one reports read: an inherited spec holds another backbone's label
        folder_spec = backbone_module(cls.name, "spec")
        if cls.__dict__.get("spec") is not getattr(import_module(folder_spec), "SPEC", None):
            raise BackboneError(f"{where}.{cls.__qualname__}: its `spec` is not {folder_spec}.SPEC (its folder's "
                                "BackboneSpec); declare `spec = SPEC`")

    @classmethod
    def lerobot_type(cls) -> str:
        """The lerobot `config.type` this backbone wraps: its spec's `lerobot_type`, else its registry name."""
        return cls.spec.lerobot_type or cls.name

    # ------------------------------------------------------------------------------ the spec, as attributes
    @property
    def image_method(self) -> str:
        return self.spec.image_method

    @property
    def vision_slots(self) -> tuple[str, str]:
        return self.spec.vision_slots

    @property
    def steps_field(self) -> str | None:
        return self.spec.steps_field

    @property
    def token_steps(self) -> tuple[str, ...]:
        return self.spec.token_steps

    @property
    def prompt_uses_state(self) -> bool:
        return self.spec.prompt_uses_state

    @property
    def module_paths(self) -> Mapping[str, tuple[str, ...]]:
        return self.spec.module_paths

    def __init__(self, policy: nn.Module, preprocessor, postprocessor, *, source: str,
                 random_init: bool, tiny_marker: dict | None = None) -> None:
        self.policy = policy
        self.preprocessor = preprocessor
        self.postprocessor = postprocessor
        self.source = source
        self.random_init = random_init
        self.tiny_marker = tiny_marker
        self._sha256: str | None = None
        self._task_cache: dict[str, tuple[torch.Tensor, torch.Tensor]] = {}

    # ------------------------------------------------------------------------------ construction
    @classmethod
    def load(cls, source: str | Path, *, device: str = "cpu", dataset_stats: dict | None = None,
             tiny: TinyBuild | None = None) -> Self:
        """Build "tiny", or load a hub id (HF cache) / checkpoint folder with its saved processors.

        `dataset_stats` (lerobot format: {"observation.state"|"action": {"mean", "std", "q01", ...}})
        is needed for "tiny" and for checkpoints saved without processors; a checkpoint's own
        processors keep their own stats.
        """
        if str(source) == "tiny":
            with quiet():
                policy, pre, post, marker = cls._build_tiny(tiny or TinyBuild(), dataset_stats, device)
            neutralise(policy.config)  # those read as the policy runs (use_amp); the tiny builders set none of the rest
            return cls(policy, pre, post, source="tiny", random_init=True, tiny_marker=marker)
        folder = resolve_source(source)
        marker = read_marker(folder)
        if marker is not None and marker["backbone"] != cls.name:
            raise BackboneError(f"{folder}: a tiny {marker['backbone']} checkpoint, not {cls.name}")
        config = cls._read_config(folder)
        config.device = device
        neutralise(config)
        cls._configure(folder, config, marker)
        weights = weights_file(folder)  # header read before anything is built: a non-safetensors file is one line
        with quiet():  # lerobot's construction chatter, and pi0.5's key renaming warns per vision key
            policy = construct(lambda: cls._construct(config, marker), config)
            try:
                keys = cls._checkpoint_keys(policy, read_header(weights)[1])
            except BackboneError as e:
                raise BackboneError(f"{weights}: {e}") from None
            load_checkpoint(policy, weights, keys, torch.device(device))
        policy.eval()  # as lerobot's from_pretrained leaves a policy (pi0.5's own override forgets to)
        processors = load_processors(folder, *cls._processor_overrides(policy.config, marker, device))
        if processors is None:
            if dataset_stats is None:
                raise BackboneError(f"{folder}: no {PREPROCESSOR_FILE}; pass dataset_stats to build the processors")
            processors = cls._make_processors(policy.config, dataset_stats, marker)
        # A tiny checkpoint is never released weights: random init, at most trained by train-tiny on a sample;
        # nor is one written at the released geometry by devtools.released.
        random_init = marker is not None or is_random_release(folder)
        return cls(policy, *processors, source=str(source), random_init=random_init, tiny_marker=marker)

    @classmethod
    def saved_config(cls, source: str | Path, device: str = "cpu"):
        """A checkpoint's policy config as `load` configures it (`_configure`, the device), without building the
        policy (graftcache.export.processors)."""
        folder = resolve_source(source)
        config = cls._read_config(folder)
        config.device = device
        cls._configure(folder, config, read_marker(folder))
        return config

    @classmethod
    def saved_processors(cls, source: str | Path, device: str = "cpu") -> tuple[Any, Any]:
        """A checkpoint's own saved (pre, post) processors, loaded as `load` loads them (its overrides: local
        tokenizers of tiny checkpoints, the device), without building the policy (graftcache.export.processors)."""
        folder = resolve_source(source)
        config = cls.saved_config(folder, device)
        processors = load_processors(folder, *cls._processor_overrides(config, read_marker(folder), device))
        if processors is None:
            raise BackboneError(f"{folder}: no {PREPROCESSOR_FILE}; a policy without saved processors cannot be run "
                                "outside graftcache")
        return processors

    @classmethod
    def postprocessor_input(cls, config, actions: torch.Tensor) -> torch.Tensor:
        """Normalised actions [..., action_dim] (what `predict` returns and an export's policy emits) as the policy's
        own postprocessor takes them, at the width the policy's `select_action` emits: as they are for most policies.
        `unnormalize` and an export's postprocessor (graftcache.export.processors) both pass actions through here."""
        return actions

    @classmethod
    def _read_config(cls, folder: Path):
        import lerobot.policies  # noqa: F401  (its __init__ registers every policy's config type)
        from lerobot.configs.policies import PreTrainedConfig

        if not (folder / "config.json").is_file():
            raise BackboneError(f"{folder}: no config.json (not a lerobot policy checkpoint)")
        try:
            config = PreTrainedConfig.from_pretrained(folder)
        except Exception as exc:  # draccus raises assorted types on a bad or foreign config
            raise BackboneError(f"{folder / 'config.json'}: not a lerobot policy config ({exc})") from None
        if config.type != cls.lerobot_type():
            raise BackboneError(f"{folder / 'config.json'}: a {config.type!r} policy, not {cls.lerobot_type()!r} "
                                f"(what backbone {cls.name!r} wraps)")
        return config

    @classmethod
    def _build_tiny(cls, tiny: TinyBuild, stats: dict | None, device: str) -> tuple[nn.Module, Any, Any, dict]:
        """Random-init tiny policy, processors and the marker that lets it be saved and reloaded: the backbone's own
        `graftcache.backbones.<name>.tiny.build_tiny` (the registry's convention: graftcache/backbone_registry.py)."""
        policy, pre, post, geometry = import_module(backbone_module(cls.name, "tiny")).build_tiny(tiny, stats, device)
        return policy, pre, post, {"backbone": cls.name, "geometry": geometry}

    @classmethod
    def _configure(cls, folder: Path, config, marker: dict | None) -> None:
        """Point `config` at what the policy reads from beside its checkpoint when it is constructed (pi0-FAST:
        its tokenizers); nothing for most policies."""

    @classmethod
    def _construct(cls, config, marker: dict | None) -> nn.Module:
        """The policy class's own constructor on `config` (`load` runs it with its parameters on the meta
        device and fills them from the checkpoint). Override to adjust the config or construct at a tiny
        marker's sizes."""
        from lerobot.policies.factory import get_policy_class

        return get_policy_class(config.type)(config)

    @classmethod
    def _checkpoint_keys(cls, policy: nn.Module, file_keys: Iterable[str]) -> dict[str, str]:
        """{policy state-dict key: checkpoint key}: each key as it is unless the policy's from_pretrained renames keys
        (pi0.5: graftcache.backbones.lean_load.openpi_keys)."""
        return {k: k for k in file_keys}

    @classmethod
    def _processor_overrides(cls, config, marker: dict | None, device: str) -> tuple[dict, dict]:
        """Per-step overrides (lerobot registry names) applied when loading saved processors."""
        device_override = {"device_processor": {"device": device}}
        return dict(device_override), dict(device_override)

    @classmethod
    @abstractmethod
    def _make_processors(cls, config, stats: dict, marker: dict | None) -> tuple[Any, Any]:
        """lerobot's processor factory for this policy, for checkpoints saved without processors."""

    def save(self, folder: str | Path) -> Path:
        """Save an ungrafted policy + processors (+ the tiny marker) so `load(folder)` restores it."""
        if self.grafted:
            raise BackboneError(f"{self.name}: a grafted policy is not a lerobot checkpoint; save before graft()")
        folder = Path(folder)
        self.policy.save_pretrained(folder)
        self.preprocessor.save_pretrained(folder)
        self.postprocessor.save_pretrained(folder)
        if self.tiny_marker is not None:
            write_marker(folder, self.tiny_marker["backbone"], self.tiny_marker["geometry"])
        follow_umask(folder)  # safetensors writes 0600 files; a shared policy must be readable by the team
        return folder

    # ------------------------------------------------------------------------------ geometry
    @property
    def config(self):
        return self.policy.config

    @property
    def device(self) -> torch.device:
        return next(self.policy.parameters()).device

    @property
    def camera_keys(self) -> tuple[str, ...]:
        """The policy's real image inputs, e.g. ("observation.images.image", "observation.images.image2")."""
        return tuple(k for k in self.config.image_features if not is_empty_camera(k))

    @property
    def cameras(self) -> tuple[str, ...]:
        """The policy's camera names, in its order (what graftcache.cameras matches a cache's cameras against)."""
        return _camera_names(self.camera_keys)

    @classmethod
    def read_cameras(cls, source: str | Path) -> tuple[str, ...]:
        """The camera names of a checkpoint from its config alone: a fit pairs them with its cache's cameras
        (and keys its rows by the pairing) before it loads anything."""
        if str(source) == "tiny":
            raise BackboneError(f"{cls.name}: an in-memory tiny policy has no checkpoint to read; load it")
        keys = cls._read_config(resolve_source(source)).image_features
        return _camera_names(k for k in keys if not is_empty_camera(k))

    @property
    def chunk_size(self) -> int:
        return self.config.chunk_size

    @property
    def action_dim(self) -> int:
        return self.config.output_features[ACTION].shape[0]

    @property
    def state_dim(self) -> int:
        return self.config.input_features[STATE].shape[0]

    @property
    def max_action_dim(self) -> int:
        """Width of the padded action vectors the flow model works in (noise has this width)."""
        return self.config.max_action_dim

    @functools.cached_property
    def token_grid(self) -> tuple[int, int]:
        """Per-camera token grid the LM sees (post-connector), of the policy's own tower."""
        return self._grid_of_config(self.config, self.tiny_marker)

    @classmethod
    def read_token_grid(cls, source: str | Path) -> tuple[int, int]:
        """The token grid of a checkpoint from its config alone: a sweep needs it to key its caches,
        and a finished sweep must not load a 3B-parameter policy to learn it."""
        if str(source) == "tiny":
            raise BackboneError(f"{cls.name}: an in-memory tiny policy has no checkpoint to read; load it")
        folder = resolve_source(source)
        return cls._grid_of_config(cls._read_config(folder), read_marker(folder))

    @classmethod
    @abstractmethod
    def _grid_of_config(cls, config, marker: dict | None) -> tuple[int, int]:
        """Per-camera post-connector token grid implied by a policy config (and the tiny marker)."""

    @property
    def lm_width(self) -> int:
        """Width of the LM's token embeddings, i.e. the projector's output width (read where `spec.lm_width` says)."""
        return int(operator.attrgetter(self.spec.lm_width)(self))

    @property
    def embed_scale(self) -> float:
        """Factor lerobot applies to image tokens after the connector (and so after a graft projector)."""
        return float(self.lm_width) ** 0.5 if self.spec.scaled_embeddings else 1.0

    # ------------------------------------------------------------------------------ native tower
    def _check_native(self, images: torch.Tensor) -> None:
        """Refuse, in one line, a native-tower read after graft() or of images not [B, 3, H, W]."""
        if self.grafted:
            raise BackboneError(f"{self.name}: the native tower was removed by graft(); read it before grafting")
        if images.ndim != 4 or images.shape[1] != 3:
            raise BackboneError(f"{self.name}: native images must be [B, 3, H, W] in [0, 1], got {tuple(images.shape)}")

    def _native_pixels(self, images: torch.Tensor) -> torch.Tensor:
        """[B, 3, H, W] in [0, 1] -> the tower's input, through the policy's own image preparation."""
        self._check_native(images)
        prepare = getattr(type(self.policy), self.image_method)
        prepared, _ = prepare(self.policy, {self.camera_keys[0]: images.to(self.device)})
        return prepared[0]

    @property
    @abstractmethod
    def _vision_owner(self) -> nn.Module:
        """The module holding the vision tower and the connector (as `vision_slots` attributes)."""

    def _vision_slots(self) -> tuple[nn.Module, str, str]:
        """(module owning the tower, tower attribute, connector attribute)."""
        return self._vision_owner, *self.vision_slots

    def _module_groups(self) -> dict[str, nn.Module | tuple[nn.Module, ...]]:
        """Named parts of the policy for the freeze report (a group of one path is that module)."""
        tower, connector = self._tower_and_connector()
        groups: dict[str, nn.Module | tuple[nn.Module, ...]] = {
            "vision tower": tower, "graft projector" if self.grafted else "connector": connector}
        for name, paths in self.module_paths.items():
            modules = tuple(operator.attrgetter(p)(self) for p in paths)
            groups[name] = modules[0] if len(modules) == 1 else modules
        return groups

    def _tower_and_connector(self) -> tuple[nn.Module, nn.Module]:
        """The native vision tower and connector modules."""
        owner, tower, connector = self._vision_slots()
        return getattr(owner, tower), getattr(owner, connector)

    @torch.no_grad()
    def native_patch_grid(self, images: torch.Tensor) -> torch.Tensor:
        """The native tower's pre-connector patch grid [B, gh, gw, C] (for the native-graft control)."""
        tower, _ = self._tower_and_connector()
        pixels = self._native_pixels(images)
        hidden = tower(pixels.to(tower.dtype)).last_hidden_state.float()
        side = int(round(hidden.shape[1] ** 0.5))
        return hidden.reshape(hidden.shape[0], side, side, hidden.shape[-1])

    @torch.no_grad()
    def native_tokens(self, images: torch.Tensor) -> torch.Tensor:
        """Post-connector tokens [B, T, D], before lerobot's `embed_scale` (native control, align target)."""
        tower, connector = self._tower_and_connector()
        pixels = self._native_pixels(images)
        return connector(tower(pixels.to(tower.dtype)).last_hidden_state).float()


    @functools.cached_property
    def n_params(self) -> int:
        """Parameters of the policy as loaded (shared ones once), what the analysis orders backbones by; counted
        (and kept) by the first graft, before it swaps the tower and connector for a pass-through and a projector."""
        if self.grafted:
            raise BackboneError(f"{self.name}: count the parameters before graft() replaces the vision tower")
        return sum(p.numel() for p in self.policy.parameters())

    @property
    def policy_sha256(self) -> str:
        """sha256 of the policy weights as loaded/built (pinned before graft() changes the modules)."""
        if self._sha256 is None:
            self._sha256 = state_dict_sha256(self.policy)
        return self._sha256
