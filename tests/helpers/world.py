"""The one test world of stage 2: a dataset, tiny policy checkpoints and the encoder caches a fit reads,
built once per module (by a module-scoped `world` fixture) and then only read.

A module says what its world is made of (which backbones, which extraction settings, whether the native
towers' caches are needed, other datasets in the same cache root) and how cheap its fits are (`fit`: steps,
eval frames, denoising steps); `request` and `fit_argv` build a fit of it in Python or on the command line.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from safetensors import safe_open

from graftcache.backbone_registry import native_name
from graftcache.extract import extract
from graftcache.requests import FitRequest
from graftcache.store import FeatureCache
from helpers.backbones import tiny
from helpers.datasets import Written
from helpers.requests import FIT, extract_request, fit_request


def _quiet(_: str) -> None:
    pass


class World:
    """`dataset` (and `others`, extracted into the same cache root), a tiny checkpoint per backbone in
    `backbones`, the cache of `encoder` with `extract_settings`, and with `native_tower_grid` each backbone's native
    tower cached at that grid."""

    def __init__(self, root: Path, dataset: Written, *, encoder: str, backbones: Sequence[str] = ("smolvla",),
                 extract_settings: dict[str, Any] | None = None, native_tower_grid: str | None = None,
                 others: Sequence[Written] = (), fit: dict[str, Any] | None = None) -> None:
        self.root, self.dataset, self.encoder, self.others = root, dataset, encoder, tuple(others)
        self.cache = root / "cache"
        self.fit = dict(fit or {})
        self.policies = {name: root / f"policy_{name}" for name in backbones}
        for name, folder in self.policies.items():
            tiny(name).save(folder)
        settings = {"encoder": encoder, **(extract_settings or {})}
        self.encoder_key = extract(extract_request(dataset.root, self.cache, **settings), log=_quiet).key
        for other in others:
            extract(extract_request(other.root, self.cache, **settings), log=_quiet)
        native = {**settings, "grids": (native_tower_grid,), "random_init": False}  # the policy's own tower, as trained
        self.native_keys = {} if native_tower_grid is None else {
            name: extract(extract_request(dataset.root, self.cache, **{**native, "encoder": native_name(name),
                                                                       "policy": str(folder)}), log=_quiet).key
            for name, folder in self.policies.items()}

    @property
    def policy(self) -> Path:
        """The first backbone's checkpoint (the only one in most worlds)."""
        return next(iter(self.policies.values()))

    @property
    def encoder_cache(self) -> FeatureCache:
        return FeatureCache(self.cache / self.encoder_key)

    def request(self, backbone: str = "smolvla", *, under: Path | None = None, **settings: Any) -> FitRequest:
        """A fit of `backbone` on this world's caches, writing under `under` (default: the world's folder)."""
        return fit_request(backbone, **{"policy": self.policies[backbone], "dataset": self.dataset.root,
                                        "cache": self.cache, "under": under or self.root, "encoder": self.encoder,
                                        **self.fit, **settings})

    def fit_argv(self, results: Path, *extra: str, dataset: Written | None = None, policy: Path | None = None,
                 cache: Path | None = None) -> list[str]:
        """`graftcache fit` of the first backbone with this world's fit settings, as a command line."""
        s = {**FIT, **self.fit}
        return ["fit", "--backbone", next(iter(self.policies)), "--policy", str(policy or self.policy),
                "--encoder", self.encoder, "--dataset", str((dataset or self.dataset).root), "--suite", s["suite"],
                "--seed", ",".join(map(str, s["seeds"])), "--steps", str(s["steps"]),
                "--batch-size", str(s["batch_size"]), "--eval-fraction", str(s["eval_fraction"]),
                "--eval-frames", str(s["eval_frames"]), "--num-denoise-steps", str(s["num_denoise_steps"]),
                "--num-workers", "0", "--cache", str(cache or self.cache), "--results", str(results), "--no-progress",
                *extra]

    def policy_params(self, backbone: str) -> int:
        """Parameters of a saved policy counted from its weights file's tensor shapes (not by graftcache)."""
        with safe_open(self.policies[backbone] / "model.safetensors", "pt") as f:
            return sum(math.prod(f.get_slice(k).get_shape()) for k in f.keys())  # noqa: SIM118 (a safe_open handle)
