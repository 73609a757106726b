"""Numerics fingerprint: does this environment compute the features a cache holds?

The cache key names what the numbers are made of (weights, recipe, dtypes), not the libraries that
compute them, so a patch release that changes nothing keeps every shared cache valid. What guards
against a release that *does* change the numbers (transformers 5 moved SmolVLM's vision position
ids: the same checkpoint and pixels give tower outputs up to 0.38 apart) is this fingerprint: at
extraction the encoder runs on a fixed probe batch generated from a seed (no data) and a compact
sketch of its fp32 outputs goes into the manifest; resuming, fitting, sharing and `verify --numerics`
run the same probe in the current environment and compare within a tolerance per compute dtype.

The sketch keeps every output's per-token detail (a position-id change moves single patches) at a
few KB: up to `SKETCH_TOKENS` evenly spaced tokens, each projected onto `SKETCH_DIMS` fixed unit-norm
random directions (so a change in any channel shows, in the features' own units). Differences are
judged relative to the recorded sketch's RMS, so one tolerance fits encoders of any scale.
"""

from __future__ import annotations

import base64
import gc
import hashlib
import math
import platform
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from importlib.metadata import PackageNotFoundError, version
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from graftcache.errors import GraftcacheError, NumericsError
from graftcache.requests import FitRequest
from graftcache.runtime import autocast, resolve_device, resolve_dtype
from graftcache.settings import flag_of

if TYPE_CHECKING:
    from graftcache.encoders.encoder import Encoder
    from graftcache.store import FeatureCache, Manifest

VERSIONED_PACKAGES = ("torch", "timm", "transformers", "lerobot", "zarr", "numcodecs", "av", "numpy")
PROBE_SEED = 0
PROBE_FRAMES = 2
PROBE_SIZE = 256  # LIBERO's frame size, so the probe also goes through the resize real frames take
SKETCH_TOKENS = 32
SKETCH_DIMS = 8
#: largest |difference| / RMS of the recorded sketch that still counts as the same numbers, per compute dtype:
#: fp32 allows CUDA's TF32 convolutions vs CPU (~1e-3), bf16 / fp16 their rounding across kernels and devices
#: the flag of every command that refuses a drifted cache unless told
ACCEPT_FLAG = flag_of(FitRequest, "accept_numerics_drift")
TOLERANCE = {"fp32": 2e-3, "fp16": 1e-2, "bf16": 5e-2}


def library_versions() -> dict[str, str]:
    """Versions of the libraries that compute or store features (recorded in every manifest)."""
    out = {"python": platform.python_version()}
    for pkg in VERSIONED_PACKAGES:
        try:
            out[pkg] = version(pkg)
        except PackageNotFoundError:
            out[pkg] = "absent"
    return out


def probe_frames(seed: int = PROBE_SEED) -> np.ndarray:
    """uint8 [PROBE_FRAMES, PROBE_SIZE, PROBE_SIZE, 3] from sha256 alone (no RNG library whose stream could
    change): a smooth pattern, as camera frames are, and full-band noise."""
    n = PROBE_SIZE * PROBE_SIZE * 3
    stream = b"".join(hashlib.sha256(f"graftcache-probe:{seed}:{i}".encode()).digest() for i in range(-(-n // 32)))
    noise = np.frombuffer(stream[:n], np.uint8).reshape(PROBE_SIZE, PROBE_SIZE, 3)
    params = np.frombuffer(stream[:9], np.uint8).astype(np.float64).reshape(3, 3) / 255
    y, x = np.mgrid[0:PROBE_SIZE, 0:PROBE_SIZE] / PROBE_SIZE
    smooth = np.stack([np.sin(2 * np.pi * (1 + 3 * a) * x + 2 * np.pi * (1 + 2 * b) * y + 6 * c)
                       for a, b, c in params], axis=-1)
    smooth = np.rint(127.5 + 120 * smooth).astype(np.uint8)
    return np.stack([smooth, noise])


def _directions(width: int) -> torch.Tensor:
    """[width, SKETCH_DIMS] unit-norm columns, fixed per width (numpy's PCG64 stream is stable)."""
    d = np.random.Generator(np.random.PCG64(width)).standard_normal((width, SKETCH_DIMS))
    return torch.from_numpy(d / np.linalg.norm(d, axis=0, keepdims=True)).float()


def sketch(tokens: torch.Tensor) -> np.ndarray:
    """[B, N, C] outputs -> fp32 [B, min(N, SKETCH_TOKENS), SKETCH_DIMS]: evenly spaced tokens, projected."""
    tokens = tokens.detach().float().cpu()
    keep = np.unique(np.linspace(0, tokens.shape[1] - 1, min(tokens.shape[1], SKETCH_TOKENS)).round().astype(int))
    return (tokens[:, torch.from_numpy(keep)] @ _directions(tokens.shape[-1])).numpy().astype(np.float32)


def probe_outputs(encoder: Encoder, compute_dtype: str, device: torch.device | str = "cpu") -> dict[str, np.ndarray]:
    """Sketches of every output the cache stores ("grid" and, for native towers, "connector"), computed the way
    extraction computes them: preprocess + forward under the cache's compute dtype, one batch."""
    device = device if isinstance(device, torch.device) else resolve_device(device)
    frames = torch.from_numpy(probe_frames()).to(device)
    with torch.inference_mode(), autocast(device, resolve_dtype(compute_dtype)):
        grid, extras = encoder.forward_with_extras(encoder.preprocess(frames))
    outputs = {"grid": grid.flatten(1, 2), **extras}
    return {name: sketch(t) for name, t in outputs.items()}


def fingerprint(encoder: Encoder, compute_dtype: str, device: torch.device | str = "cpu") -> dict[str, Any]:
    """The manifest entry: which probe (seed, size, sha256 of its frames), compute dtype, device and the encoded
    sketches."""
    return {"probe": {"seed": PROBE_SEED, "frames": PROBE_FRAMES, "size": PROBE_SIZE, "sketch_tokens": SKETCH_TOKENS,
                      "sketch_dims": SKETCH_DIMS, "sha256": hashlib.sha256(probe_frames().tobytes()).hexdigest()},
            "compute_dtype": compute_dtype, "device": str(device),
            "outputs": {name: _encode(a) for name, a in probe_outputs(encoder, compute_dtype, device).items()}}


def _encode(a: np.ndarray) -> dict[str, Any]:
    return {"shape": list(a.shape), "fp32": base64.b64encode(a.astype("<f4").tobytes()).decode()}


def _decode(entry: Mapping[str, Any]) -> np.ndarray:
    return np.frombuffer(base64.b64decode(entry["fp32"]), "<f4").reshape(entry["shape"])


@dataclass(frozen=True)
class NumericsCheck:
    """The verdict of one fingerprint comparison. status: "match" | "drift" | "unchecked" (`reason` says why)."""

    cache: str
    status: str
    drift: float | None = None          # largest |difference| / RMS of the recorded sketch, over the outputs
    largest: float | None = None        # that largest |difference|, in the features' own units
    output: str | None = None           # which output it is in ("grid", "connector")
    compute_dtype: str | None = None
    tolerance: float | None = None
    versions: dict[str, tuple[str, str]] = field(default_factory=dict)  # package -> (recorded, now), differing only
    reason: str = ""

    def versions_text(self) -> str:
        if not self.versions:
            return "no recorded library version differs"
        return "versions differ: " + ", ".join(f"{p} {a} -> {b}" for p, (a, b) in sorted(self.versions.items()))

    def line(self) -> str:
        """One line: the cache, the largest difference against the tolerance, and the differing versions."""
        if self.status == "unchecked":
            return f"cache {self.cache}: numerics not checked: {self.reason}"
        verdict = "this environment computes different features than the one that made it" \
            if self.status == "drift" else "numerics match this environment"
        return (f"cache {self.cache}: {verdict}: largest probe difference {self.largest:.3g} in the {self.output} "
                f"output ({self.drift:.2%} of its RMS; {self.compute_dtype} tolerance {self.tolerance:.2%}); "
                f"{self.versions_text()}")

    def require_match(self, remedy: str) -> None:
        """Raise NumericsError (this line + what to do) when the numbers drifted."""
        if self.status == "drift":
            raise NumericsError(f"{self.line()}; {remedy}")

    def enforce(self, command: str, *, accept: bool, log: Callable[[str], None], unchecked: str = "") -> None:
        """What a command that uses a cache does with the verdict (fit, push, pull): drift is refused unless
        `accept` (the user's --accept-numerics-drift), then said; an unchecked cache is a warning (plus what the
        command does about it, `unchecked`)."""
        if self.status == "unchecked":
            log(f"warning: {self.line()}" + (f"; {unchecked}" if unchecked else ""))
        elif self.status == "drift" and not accept:
            self.require_match(f"{command} refuses it; pass {ACCEPT_FLAG} to {command} anyway")
        elif self.status == "drift":
            log(f"warning: {self.line()}; {command} goes on ({ACCEPT_FLAG})")


def compare(cache: str, recorded: Mapping[str, Any], current: Mapping[str, Any],
            recorded_versions: Mapping[str, str] | None = None) -> NumericsCheck:
    """Compare two fingerprints (the manifest's and one computed now)."""
    versions = {p: (str(v), library_versions().get(p, "absent")) for p, v in (recorded_versions or {}).items()}
    versions = {p: ab for p, ab in versions.items() if ab[0] != ab[1]}
    dtype = str(recorded.get("compute_dtype"))
    if recorded.get("probe") != current.get("probe"):
        return NumericsCheck(cache, "unchecked", compute_dtype=dtype, versions=versions,
                             reason="its fingerprint was made with another probe than this graftcache version's")
    if set(recorded["outputs"]) != set(current["outputs"]):
        return NumericsCheck(cache, "unchecked", compute_dtype=dtype, versions=versions,
                             reason=f"it records outputs {sorted(recorded['outputs'])}, the encoder here gives "
                                    f"{sorted(current['outputs'])}")
    worst = (-1.0, 0.0, "")
    for name, entry in recorded["outputs"].items():
        was, now = _decode(entry), _decode(current["outputs"][name])
        if was.shape != now.shape:
            worst = max(worst, (math.inf, math.inf, name))
            continue
        largest = float(np.abs(now.astype(np.float64) - was).max()) if was.size else 0.0
        rms = float(np.sqrt(np.mean(np.square(was, dtype=np.float64)))) if was.size else 0.0
        worst = max(worst, (largest / max(rms, 1e-12) if largest else 0.0, largest, name))
    drift, largest, output = worst
    tolerance = TOLERANCE.get(dtype, TOLERANCE["fp32"])
    return NumericsCheck(cache, "match" if drift <= tolerance else "drift", drift, largest, output, dtype, tolerance,
                         versions)


def check_numerics(cache: FeatureCache, *, device: str | torch.device = "cpu",
                   encoder: Encoder | None = None) -> NumericsCheck:
    """Recompute a cache's probe in this environment and compare it with the manifest's fingerprint.

    The one entry point for every place that uses an existing cache (resume, fit, push/pull, verify).
    The encoder is rebuilt from the manifest (registry name + the recorded weights source) unless given;
    when that is impossible here (weights absent, a cache made before fingerprints) the result is
    "unchecked" with the reason, never a silent match. Raise with `.require_match(remedy)`.
    """
    manifest = cache.manifest
    if encoder is not None:
        return _check_with(cache, encoder, device)
    try:
        loaded = encoder_of(manifest, device)
    except GraftcacheError as e:
        return NumericsCheck(cache.key, "unchecked", reason=f"its encoder cannot be loaded here ({e})")
    try:
        return _check_with(cache, loaded, device)
    finally:
        # A native tower is a whole policy (a released pi0.5: 9 GB on the device), and some adapters' method
        # shadows make it a reference cycle: collect it now, before the fit loads its own copy, not whenever the
        # garbage collector next runs.
        del loaded
        gc.collect()
        if torch.device(device).type == "cuda":
            torch.cuda.empty_cache()


def _check_with(cache: FeatureCache, encoder: Encoder, device: str | torch.device) -> NumericsCheck:
    manifest = cache.manifest
    recorded = manifest.numerics
    if encoder.weights_info.get("sha256") != manifest.weights_sha256:
        return NumericsCheck(cache.key, "unchecked", reason=f"the weights found here (sha256 "
                             f"{str(encoder.weights_info.get('sha256'))[:12]}...) are not the ones it was made with "
                             f"({manifest.weights_sha256[:12]}...)")
    current = fingerprint(encoder, recorded["compute_dtype"], device)
    return compare(cache.key, recorded, current, manifest.versions)


def encoder_of(manifest: Manifest, device: str | torch.device = "cpu") -> Encoder:
    """The encoder a manifest was extracted with, loaded the same way (registry name + recorded weights source)."""
    from graftcache.encoders.registry import load_encoder

    weights = manifest.weights
    source, ref = weights.get("source"), weights.get("ref")
    return load_encoder(manifest.encoder_name, device=device, random_init=source == "random-init",
                        seed=weights.get("seed"), weights=ref if source == "file" else None,
                        policy=ref if source == "policy" else None)
