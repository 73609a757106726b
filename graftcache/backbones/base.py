"""The backbone interface: one lerobot VLA policy, frozen, with the graft surgery and the objectives.

An adapter wraps lerobot's own policy object and its own pre/post processors (normalisation stats
included); it re-implements no model code. It adds what graftcache needs around them:

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
from abc import ABC, abstractmethod
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, ClassVar, Self

import torch
from torch import nn

from graftcache.backbones.checkpoint import (
    PREPROCESSOR_FILE,
    follow_umask,
    load_processors,
    quiet,
    resolve_source,
    state_dict_sha256,
    verify_weights,
    weights_file,
)
from graftcache.backbones.released import is_random_release
from graftcache.backbones.tiny import TinySpec, read_marker, write_marker
from graftcache.errors import BackboneError
from graftcache.graft import FreezeReport, PassThroughTower, feature_key, freeze_all_but, freeze_report

TOKENS = "observation.language.tokens"
TOKEN_MASK = "observation.language.attention_mask"
STATE = "observation.state"
ACTION = "action"
ACTION_PAD = "action_is_pad"
#: Projections of a Llama / Gemma decoder layer that the `lora` control adapts (attention and MLP).
LORA_TARGETS = ("q_proj", "k_proj", "v_proj", "o_proj", "gate_proj", "up_proj", "down_proj")


def is_empty_camera(key: str) -> bool:
    """lerobot's placeholder camera slots (`empty_cameras`): masked out, never fed real images."""
    return key.rsplit(".", 1)[-1].startswith("empty_camera_")


class BackboneAdapter(ABC):
    """A frozen lerobot VLA policy that a projector can be grafted onto."""

    name: ClassVar[str]
    image_method: ClassVar[str]              # policy method turning a batch into (images, masks)
    token_steps: ClassVar[tuple[str, ...]]   # preprocessor steps that build the prompt tokens
    prompt_uses_state: ClassVar[bool] = False

    def __init__(self, policy: nn.Module, preprocessor, postprocessor, *, source: str,
                 random_init: bool, tiny_marker: dict | None = None) -> None:
        self.policy = policy
        self.preprocessor = preprocessor
        self.postprocessor = postprocessor
        self.source = source
        self.random_init = random_init
        self.tiny_marker = tiny_marker
        self.projector: nn.Module | None = None
        self._sha256: str | None = None
        self._task_cache: dict[str, tuple[torch.Tensor, torch.Tensor]] = {}
        self._pristine: dict[str, torch.Tensor] | None = None  # CPU copy of the loaded weights (see reset())
        self._undo: list[tuple[nn.Module, str, nn.Module]] = []  # (owner, attribute, original module)
        self._requires_grad: dict[str, bool] = {}
        self._lora_host: nn.Module | None = None

    # ------------------------------------------------------------------------------ construction
    @classmethod
    def load(cls, source: str | Path, *, device: str = "cpu", dataset_stats: dict | None = None,
             tiny: TinySpec | None = None) -> Self:
        """Build "tiny", or load a hub id (HF cache) / checkpoint folder with its saved processors.

        `dataset_stats` (lerobot format: {"observation.state"|"action": {"mean", "std", "q01", ...}})
        is needed for "tiny" and for checkpoints saved without processors; a checkpoint's own
        processors keep their own stats.
        """
        if str(source) == "tiny":
            with quiet():
                policy, pre, post, marker = cls._build_tiny(tiny or TinySpec(), dataset_stats, device)
            return cls(policy, pre, post, source="tiny", random_init=True, tiny_marker=marker)
        folder = resolve_source(source)
        marker = read_marker(folder)
        if marker is not None and marker["backbone"] != cls.name:
            raise BackboneError(f"{folder}: a tiny {marker['backbone']} checkpoint, not {cls.name}")
        config = cls._read_config(folder)
        config.device = device
        weights = weights_file(folder)  # header read before lerobot's load: a non-safetensors file is one line
        with quiet():  # lerobot's loading chatter, and pi0.5's key renaming warns per vision key
            policy = cls._load_policy(folder, config, marker)
            verify_weights(policy, weights, cls._checkpoint_key_map(policy))
        processors = load_processors(folder, *cls._processor_overrides(policy.config, marker, device))
        if processors is None:
            if dataset_stats is None:
                raise BackboneError(f"{folder}: no {PREPROCESSOR_FILE}; pass dataset_stats to build the processors")
            processors = cls._make_processors(policy.config, dataset_stats, marker)
        # A tiny checkpoint is never released weights: random init, at most trained natively on a sample;
        # nor is one written at the released geometry by graftcache.backbones.released.
        random_init = marker is not None or is_random_release(folder)
        return cls(policy.to(device), *processors, source=str(source), random_init=random_init,
                   tiny_marker=marker)

    @classmethod
    def _read_config(cls, folder: Path):
        import lerobot.policies.pi05.configuration_pi05  # noqa: F401  (registers the config types)
        import lerobot.policies.smolvla.configuration_smolvla  # noqa: F401
        from lerobot.configs.policies import PreTrainedConfig

        if not (folder / "config.json").is_file():
            raise BackboneError(f"{folder}: no config.json (not a lerobot policy checkpoint)")
        try:
            config = PreTrainedConfig.from_pretrained(folder)
        except Exception as exc:  # draccus raises assorted types on a bad or foreign config
            raise BackboneError(f"{folder / 'config.json'}: not a lerobot policy config ({exc})") from None
        if config.type != cls.name:
            raise BackboneError(f"{folder / 'config.json'}: a {config.type!r} policy, not {cls.name!r}")
        return config

    @classmethod
    @abstractmethod
    def _build_tiny(cls, spec: TinySpec, stats: dict | None, device: str) -> tuple[nn.Module, Any, Any, dict]:
        """Random-init tiny policy, processors and the marker that lets it be saved and reloaded."""

    @classmethod
    @abstractmethod
    def _load_policy(cls, folder: Path, config, marker: dict | None) -> nn.Module:
        """The policy class's own `from_pretrained` on `folder` with `config`."""

    @classmethod
    def _checkpoint_key_map(cls, policy: nn.Module):
        """{file key: shape} -> {policy key: shape}; identity unless the policy renames keys on load."""
        return dict

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
        return tuple(k.removeprefix("observation.images.") for k in self.camera_keys)

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
    def native_grid(self) -> tuple[int, int]:
        """Per-camera token grid the LM sees natively (post-connector)."""
        return self._grid_of_config(self.config, self.tiny_marker)

    @classmethod
    def read_native_grid(cls, source: str | Path) -> tuple[int, int]:
        """The native token grid of a checkpoint from its config alone: a sweep needs it to key its caches,
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
    @abstractmethod
    def lm_width(self) -> int:
        """Width of the LM's token embeddings, i.e. the projector's output width."""

    @property
    @abstractmethod
    def embed_scale(self) -> float:
        """Factor lerobot applies to image tokens after the connector (and so after a graft projector)."""

    # ------------------------------------------------------------------------------ surgery
    @abstractmethod
    def _vision_slots(self) -> tuple[nn.Module, str, str]:
        """(module owning the tower, tower attribute, connector attribute)."""

    @property
    def grafted(self) -> bool:
        return self.projector is not None

    def graft(self, projector: nn.Module) -> None:
        """Replace tower and connector, read images from cached features, freeze all but `projector`."""
        if self.grafted:
            raise BackboneError(f"{self.name}: already grafted")
        width = getattr(projector, "out_features", None)
        if width != self.lm_width:
            raise BackboneError(f"{self.name}: projector outputs width {width}, the LM expects {self.lm_width}")
        _ = self.policy_sha256  # pin the hash of the loaded weights before the surgery changes them
        if self._pristine is None:
            self._pristine = {k: v.detach().to("cpu", copy=True) for k, v in self.policy.state_dict().items()}
        self._requires_grad = {n: p.requires_grad for n, p in self.policy.named_parameters()}
        owner, tower, connector = self._vision_slots()
        projector = projector.to(self.device)
        self._replace(owner, tower, PassThroughTower().to(self.device))
        self._replace(owner, connector, projector)
        setattr(self.policy, self.image_method, self._feature_images)
        freeze_all_but(self.policy, projector)
        self.projector = projector

    def _replace(self, owner: nn.Module, attribute: str, module: nn.Module) -> None:
        """setattr that remembers the module it replaced, so reset() can undo the surgery."""
        self._undo.append((owner, attribute, getattr(owner, attribute)))
        setattr(owner, attribute, module)

    def reset(self) -> None:
        """Back to the policy as loaded: undo graft and LoRA surgery, restore the requires_grad flags and
        the weights from the CPU copy kept at the first graft(). Lets one loaded backbone serve every
        cell of a run (a released pi0.5 is 3.3B parameters: reloading it per cell costs more than a fit)."""
        while self._undo:
            owner, attribute, original = self._undo.pop()
            setattr(owner, attribute, original)
        self.policy.__dict__.pop(self.image_method, None)  # the instance override set by graft()
        if self._lora_host is not None:
            self._lora_host.__dict__.pop("peft_config", None)
            self._lora_host = None
        for name, param in self.policy.named_parameters():
            param.requires_grad_(self._requires_grad.get(name, param.requires_grad))
        if self._pristine is not None:
            self.policy.load_state_dict(self._pristine, strict=True)
        self.projector = None

    def _feature_images(self, batch: Mapping[str, Any]) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
        """Grafted stand-in for the policy's image preparation: cached features instead of pixels."""
        feats = {k: batch.get(feature_key(k)) for k in self.camera_keys}
        first = None
        for key, f in feats.items():
            if f is None:
                raise BackboneError(f"{self.name} batch has no {feature_key(key)} (camera {key})")
            if f.ndim != 3 or f.shape[-1] != self.projector.in_features:
                raise BackboneError(
                    f"{feature_key(key)}: expected [B, T, {self.projector.in_features}] features, got {tuple(f.shape)}"
                )
            first = f if first is None else first
        images, masks = [], []
        for key in self.config.image_features:
            f = feats.get(key)
            real = f is not None
            images.append(f if real else torch.zeros_like(first))
            masks.append(torch.full((first.shape[0],), real, dtype=torch.bool, device=first.device))
        return images, masks

    # ------------------------------------------------------------------------------ native tower
    def _native_pixels(self, images: torch.Tensor) -> torch.Tensor:
        """[B, 3, H, W] in [0, 1] -> the tower's input, through the policy's own image preparation."""
        if self.grafted:
            raise BackboneError(f"{self.name}: the native tower was removed by graft(); read it before grafting")
        if images.ndim != 4 or images.shape[1] != 3:
            raise BackboneError(f"{self.name}: native images must be [B, 3, H, W] in [0, 1], got {tuple(images.shape)}")
        prepared, _ = getattr(type(self.policy), self.image_method)(self.policy, {self.camera_keys[0]: images.to(self.device)})
        return prepared[0]

    @abstractmethod
    def _tower_and_connector(self) -> tuple[nn.Module, nn.Module]:
        """The native vision tower and connector modules."""

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

    # ------------------------------------------------------------------------------ batches
    def prepare(self, raw: Mapping[str, Any]) -> dict[str, Any]:
        """Raw batch -> policy batch via lerobot's preprocessor (normalisation, tokens, device).

        `raw` holds `observation.vis_feats.<camera>` [B, T, C] (grafted) or `observation.images.<camera>`
        [B, 3, H, W] in [0, 1] (native policy), `observation.state` [B, S] and `task` (list of B
        strings), plus for training `action` [B, chunk, A] and `action_is_pad` [B, chunk].
        """
        batch = dict(raw)
        wanted = [feature_key(k) if self.grafted else k for k in self.camera_keys] + [STATE, "task"]
        missing = [k for k in wanted if k not in batch]
        if missing:
            raise BackboneError(f"{self.name} batch is missing {', '.join(missing)}")
        if self.prompt_uses_state:
            return self.preprocessor(batch)
        tasks = batch.pop("task")
        tasks = [tasks] if isinstance(tasks, str) else list(tasks)
        out = self._preprocessor_without_tokens(batch)
        ids, mask = self.task_tokens(tasks)
        out[TOKENS], out[TOKEN_MASK], out["task"] = ids.to(self.device), mask.to(self.device), tasks
        return out

    @functools.cached_property
    def _token_steps(self) -> list:
        return [s for s in self.preprocessor.steps if type(s).__name__ in self.token_steps]

    @functools.cached_property
    def _preprocessor_without_tokens(self):
        pre = self.preprocessor
        steps = [s for s in pre.steps if type(s).__name__ not in self.token_steps]
        return type(pre)(steps=steps, name=pre.name, to_transition=pre.to_transition, to_output=pre.to_output)

    def task_tokens(self, tasks: Sequence[str]) -> tuple[torch.Tensor, torch.Tensor]:
        """Token ids [N, L] and attention mask [N, L] for task strings, tokenised once per distinct task.

        Padding follows the preprocessor's tokenizer step (e.g. SmolVLA pads to the longest prompt of
        the batch), so the result equals lerobot's own per-batch tokenisation.
        """
        if self.prompt_uses_state:
            raise BackboneError(f"{self.name} prompts embed the discretised state: tokenise per batch with prepare()")
        from lerobot.processor.converters import create_transition
        from lerobot.processor import TransitionKey

        for task in dict.fromkeys(tasks):
            if task not in self._task_cache:
                transition = create_transition(observation={}, complementary_data={"task": [task]})
                for step in self._token_steps:
                    transition = step(transition)
                obs = transition[TransitionKey.OBSERVATION]
                self._task_cache[task] = (obs[TOKENS][0].cpu(), obs[TOKEN_MASK][0].cpu())
        tokenizer_step = self._token_steps[-1]
        rows = [self._task_cache[t] for t in tasks]
        length = max(len(ids) for ids, _ in rows)
        ids = torch.full((len(rows), length), tokenizer_step.input_tokenizer.pad_token_id, dtype=torch.long)
        mask = torch.zeros((len(rows), length), dtype=torch.bool)
        for i, (row_ids, row_mask) in enumerate(rows):
            cols = slice(0, len(row_ids)) if tokenizer_step.padding_side == "right" else slice(length - len(row_ids), length)
            ids[i, cols], mask[i, cols] = row_ids, row_mask
        return ids, mask

    def sample_noise(self, batch_size: int, generator: torch.Generator | None = None) -> torch.Tensor:
        """Flow-matching start noise [B, chunk, max_action_dim] (on CPU from `generator`, then moved)."""
        noise = torch.randn(batch_size, self.chunk_size, self.max_action_dim, generator=generator)
        return noise.to(self.device)

    # ------------------------------------------------------------------------------ objectives
    @abstractmethod
    def _flow_losses(self, batch: Mapping[str, Any], noise: torch.Tensor | None,
                     time: torch.Tensor | None) -> torch.Tensor:
        """lerobot's per-element flow-matching loss [B, chunk, max_action_dim] (no masking)."""

    def loss(self, batch: Mapping[str, Any], noise: torch.Tensor | None = None,
             time: torch.Tensor | None = None) -> torch.Tensor:
        """Per-sample flow loss [B]: mean over real action dims and the chunk steps that are not padding.

        `noise` [B, chunk, max_action_dim] and `time` [B] default to the model's own samplers (global RNG).
        """
        batch_size = batch[STATE].shape[0]
        noise = self.sample_noise(batch_size) if noise is None else noise
        time = self.policy.model.sample_time(batch_size, self.device) if time is None else time
        losses = self._flow_losses(batch, noise, time)[:, :, : self.action_dim]
        pad = batch.get(ACTION_PAD)
        valid = torch.ones(losses.shape[:2], device=losses.device) if pad is None else (~pad.bool()).float()
        per_step = losses.mean(dim=2)
        return (per_step * valid).sum(dim=1) / valid.sum(dim=1).clamp(min=1.0)

    @abstractmethod
    def _predict_chunk(self, batch: Mapping[str, Any], noise: torch.Tensor, num_steps: int) -> torch.Tensor:
        """The policy's `predict_action_chunk` with the given noise and number of denoising steps."""

    @property
    @abstractmethod
    def num_steps(self) -> int:
        """Default number of denoising steps (from the policy config)."""

    def predict(self, batch: Mapping[str, Any], noise: torch.Tensor | None = None,
                num_steps: int | None = None) -> torch.Tensor:
        """Normalised action chunk [B, chunk, action_dim]; deterministic for a fixed `noise`."""
        batch = {k: v for k, v in batch.items() if k not in (ACTION, ACTION_PAD)}
        if noise is None:
            noise = self.sample_noise(batch[STATE].shape[0])
        was_training = self.policy.training
        try:
            return self._predict_chunk(batch, noise.to(self.device), num_steps or self.num_steps)
        finally:
            self.policy.train(was_training)

    def unnormalize(self, actions: torch.Tensor) -> torch.Tensor:
        """Normalised action chunk -> raw action units, through lerobot's postprocessor."""
        return self.postprocessor(actions)

    # ------------------------------------------------------------------------------ reporting
    @abstractmethod
    def _module_groups(self) -> dict[str, nn.Module | tuple[nn.Module, ...]]:
        """Named parts of the policy for the freeze report."""

    def add_lora(self, rank: int, alpha: float | None = None) -> None:
        """The `lora` control: peft LoRA adapters on the language model's projections, trained together
        with the projector. The adapters are injected in place (lerobot calls the layers' projections
        directly, not the LM's forward); their B matrices start at zero, so before training the policy
        computes exactly what the plain graft does. Only the adapters become trainable in the LM."""
        from peft import LoraConfig, inject_adapter_in_model

        if not self.grafted:
            raise BackboneError(f"{self.name}: add LoRA after graft(), so the projector and adapters train together")
        lm = self._module_groups()["language model"]
        config = LoraConfig(r=rank, lora_alpha=alpha or rank, lora_dropout=0.0, bias="none",
                            target_modules=list(LORA_TARGETS))
        inject_adapter_in_model(config, lm)
        self._lora_host = lm  # peft records its config on the module: dropped again by reset()
        for owner in list(lm.modules()):
            for attribute, child in list(owner.named_children()):
                base = getattr(child, "base_layer", None)
                if isinstance(base, nn.Module):  # a peft LoRA layer wrapping the original projection
                    self._undo.append((owner, attribute, base))
        for name, param in lm.named_parameters():
            param.requires_grad_("lora_" in name)

    def freeze_report(self) -> FreezeReport:
        return freeze_report(self._module_groups(), self.policy)

    @property
    def policy_sha256(self) -> str:
        """sha256 of the policy weights as loaded/built (pinned before graft() changes the modules)."""
        if self._sha256 is None:
            self._sha256 = state_dict_sha256(self.policy)
        return self._sha256
