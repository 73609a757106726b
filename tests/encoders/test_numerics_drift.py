"""The numerics fingerprint: an environment that computes other features than the one that made a cache is
caught at resume, fit and verify (a nudged weight; SmolVLM's vision position ids as transformers 4.57 computed
them), an unchanged one passes."""

from __future__ import annotations

import json
from functools import partial
from importlib.metadata import version
from pathlib import Path

import numpy as np
import pytest
import torch
import transformers
from helpers.backbones import tiny
from helpers.datasets import Written
from helpers.requests import extract_request
from helpers.world import World
from transformers.models.smolvlm import modeling_smolvlm

import graftcache.extract
from graftcache import results
from graftcache.backbone_registry import native_name
from graftcache.cli import main
from graftcache.encoders import fingerprint as fp
from graftcache.encoders import registry
from graftcache.errors import NumericsError
from graftcache.extract import extract
from graftcache.fit import materials as run_module  # where a request's cells probe their caches
from graftcache.fit.local import Fitter
from graftcache.store import FeatureCache

ENCODER = "timm:vit_tiny_patch16_224"  # a real ViT architecture, cheap on CPU
NUDGE = 0.1  # added to one weight of the first convolution (ViT patch embedding / CNN stem); |w| ~ 0.02 there


def _quiet(_: str) -> None:
    pass


EXTRACT = {"grids": ("2x2",), "seed": 0, "batch_size": 4, "block_frames": 4, "compute_dtype": "fp32"}
_req = partial(extract_request, encoder=ENCODER, **EXTRACT)


def nudge(monkeypatch: pytest.MonkeyPatch) -> None:
    """Every encoder built from here on has one weight nudged after its weights were hashed: the same weights
    file, computed differently, as a library change would."""
    original = registry._builder_of

    def builder_of(spec):
        build = original(spec)

        def nudged_build(spec, req):
            encoder = build(spec, req)
            weight = next(p for p in encoder.model.parameters() if p.ndim == 4)
            with torch.no_grad():
                weight.view(-1)[0] += NUDGE
            return encoder

        return nudged_build

    monkeypatch.setattr(registry, "_builder_of", builder_of)


def _legacy_position_ids(self, pixel_values: torch.Tensor, patch_attention_mask: torch.Tensor) -> torch.Tensor:
    """SmolVLMVisionEmbeddings.forward with the position ids transformers 4.57.6 gave SmolVLA's tower, measured as
    [0, 0, 1, ..., n-2] along each axis (5.x: [0, 1, ..., n-1]); full images, so no patch is masked."""
    embeddings = self.patch_embedding(pixel_values).flatten(2).transpose(1, 2)
    rows, cols = (pixel_values.shape[-2] // self.patch_size, pixel_values.shape[-1] // self.patch_size)
    r = (torch.arange(rows) - 1).clamp(min=0)
    c = (torch.arange(cols) - 1).clamp(min=0)
    ids = (r[:, None] * self.num_patches_per_side + c[None, :]).reshape(1, -1).to(pixel_values.device)
    return embeddings + self.position_embedding(ids.expand(pixel_values.shape[0], -1))


# ------------------------------------------------------------------------------------------------ the probe
def test_probe_is_fixed_by_its_seed_and_the_fingerprint_is_a_few_kb() -> None:
    frames = fp.probe_frames()
    assert frames.shape == (fp.PROBE_FRAMES, fp.PROBE_SIZE, fp.PROBE_SIZE, 3) and frames.dtype == np.uint8
    np.testing.assert_array_equal(frames, fp.probe_frames(fp.PROBE_SEED))
    assert not np.array_equal(frames, fp.probe_frames(fp.PROBE_SEED + 1))
    steps = np.abs(np.diff(frames.astype(int), axis=2)).mean(axis=(1, 2, 3))
    assert steps[0] < 8 < 60 < steps[1]  # one smooth frame, one full-band noise frame
    encoder = registry.load_encoder(ENCODER, random_init=True)
    entry = fp.fingerprint(encoder, "fp32")
    assert len(json.dumps(entry)) < 8000
    sketch = fp._decode(entry["outputs"]["grid"])
    assert sketch.dtype == np.float32 and sketch.shape == (fp.PROBE_FRAMES, fp.SKETCH_TOKENS, fp.SKETCH_DIMS)
    # the sketch is the grid's evenly spaced tokens seen along unit directions, computed here independently
    with torch.no_grad():
        grid = encoder.forward_grid(encoder.preprocess(torch.from_numpy(frames))).flatten(1, 2)
    keep = np.linspace(0, grid.shape[1] - 1, fp.SKETCH_TOKENS).round().astype(int)
    dirs = np.random.Generator(np.random.PCG64(grid.shape[-1])).standard_normal((grid.shape[-1], fp.SKETCH_DIMS))
    want = grid.numpy()[:, keep] @ (dirs / np.linalg.norm(dirs, axis=0))
    np.testing.assert_allclose(sketch, want, rtol=1e-4, atol=1e-5)


def test_compare_judges_relative_to_the_recorded_scale_per_dtype() -> None:
    was = {"probe": {"seed": 0}, "compute_dtype": "bf16", "outputs": {"grid": fp._encode(np.full((1, 4, 2), 10.0))}}
    near = {**was, "outputs": {"grid": fp._encode(np.full((1, 4, 2), 10.4))}}  # 4% of the RMS
    far = {**was, "outputs": {"grid": fp._encode(np.full((1, 4, 2), 11.0))}}
    assert fp.compare("k", was, near).status == "match"  # within bf16's 5%
    check = fp.compare("k", was, far, {"torch": "0.0.1"})
    assert check.status == "drift" and check.largest == pytest.approx(1.0) and check.drift == pytest.approx(0.1)
    assert check.versions == {"torch": ("0.0.1", version("torch"))}
    assert fp.compare("k", {**was, "compute_dtype": "fp32"}, {**near, "compute_dtype": "fp32"}).status == "drift"
    assert fp.compare("k", was, {**far, "probe": {"seed": 1}}).status == "unchecked"


# ------------------------------------------------------------------------------------------------ extraction
@pytest.fixture(scope="module")
def made(v3_image: Written, tmp_path_factory: pytest.TempPathFactory) -> FeatureCache:
    root = tmp_path_factory.mktemp("numerics_cache")
    return FeatureCache(extract(_req(v3_image.root, root), log=_quiet).path)


def test_an_unchanged_environment_passes(made: FeatureCache, capsys: pytest.CaptureFixture) -> None:
    recorded = made.manifest.numerics
    assert recorded["compute_dtype"] == "fp32" and set(recorded["outputs"]) == {"grid"}
    check = fp.check_numerics(made)
    assert check.status == "match" and check.drift <= fp.TOLERANCE["fp32"] and check.output == "grid"
    assert main(["verify", made.key, "--cache", str(made.path.parent), "--numerics"]) == 0
    assert f"cache {made.key}: numerics match this environment" in capsys.readouterr().out


def test_the_fingerprint_does_not_enter_the_key(made: FeatureCache) -> None:
    from graftcache.store import cache_key

    manifest = made.manifest.to_dict()
    assert cache_key(manifest) == made.key
    changed = {**manifest, "versions": {**manifest["versions"], "transformers": "4.57.6"},
               "numerics": {**manifest["numerics"], "outputs": {}}}
    assert cache_key(changed) == made.key


def _interrupted(dataset: Path, root: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A cache whose extraction stopped after its first block (writing the second failed; the writer thread
    writes blocks in order, so block 0 is durably done when the error surfaces)."""
    write = FeatureCache.write_block

    def failing(self, block, data):
        if block > 0:
            raise RuntimeError("interrupted")
        write(self, block, data)

    with monkeypatch.context() as m:
        m.setattr(FeatureCache, "write_block", failing)
        with pytest.raises(RuntimeError, match="interrupted"):
            extract(_req(dataset, root), log=_quiet)
    (path,) = [p for p in root.iterdir() if p.is_dir()]
    assert FeatureCache(path).blocks_done() == {0} and not FeatureCache(path).complete
    return path


def test_resuming_in_a_perturbed_environment_is_refused(v3_image: Written, tmp_path: Path,
                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    path = _interrupted(v3_image.root, tmp_path, monkeypatch)
    nudge(monkeypatch)
    with pytest.raises(NumericsError) as err:
        extract(_req(v3_image.root, tmp_path), log=_quiet)
    message = str(err.value)
    assert "\n" not in message and message.startswith(f"cache {path.name}: this environment computes different")
    assert "largest probe difference" in message and f"delete {path}" in message
    assert not FeatureCache(path).complete


def test_resuming_in_the_same_environment_finishes_the_cache(v3_image: Written, tmp_path: Path,
                                                             monkeypatch: pytest.MonkeyPatch,
                                                             made: FeatureCache) -> None:
    path = _interrupted(v3_image.root, tmp_path, monkeypatch)
    lines: list[str] = []
    result = extract(_req(v3_image.root, tmp_path), log=lines.append)
    assert result.path == path and FeatureCache(path).complete and any("resuming" in ln for ln in lines)
    np.testing.assert_array_equal(FeatureCache(path).read_features("image", "2x2").numpy(),
                                  made.read_features("image", "2x2").numpy())


def test_reusing_a_complete_cache_in_a_perturbed_environment_warns(made: FeatureCache, v3_image: Written,
                                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    nudge(monkeypatch)
    lines: list[str] = []
    assert extract(_req(v3_image.root, made.path.parent), log=lines.append).reused
    assert any(ln.startswith(f"warning: cache {made.key}: this environment computes different") for ln in lines)


def test_verify_reports_the_difference(made: FeatureCache, monkeypatch: pytest.MonkeyPatch,
                                       capsys: pytest.CaptureFixture) -> None:
    nudge(monkeypatch)
    assert main(["verify", made.key, "--cache", str(made.path.parent), "--numerics"]) == 1
    out = capsys.readouterr().out.splitlines()
    assert out[0].endswith("all checksums match")
    assert out[1].startswith(f"cache {made.key}: this environment computes different features")
    check = fp.check_numerics(made)
    assert f"largest probe difference {check.largest:.3g} in the grid output" in out[1]
    assert check.status == "drift" and check.drift > fp.TOLERANCE["fp32"]


def test_pull_and_push_refuse_drift_unless_accepted(made: FeatureCache, tmp_path: Path,
                                                   monkeypatch: pytest.MonkeyPatch,
                                                   capsys: pytest.CaptureFixture) -> None:
    source = str(made.path.parent)
    assert main(["pull", made.key, source, "--cache", str(tmp_path / "same")]) == 0  # unchanged: copied
    assert FeatureCache(tmp_path / "same" / made.key).complete
    nudge(monkeypatch)
    capsys.readouterr()
    for command, args in (("pull", [made.key, source, "--cache", str(tmp_path / "pulled")]),
                          ("push", [made.key, str(tmp_path / "pushed"), "--cache", source])):
        assert main([command, *args]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and f"cache {made.key}: this environment computes different features" in err
        assert f"{command} refuses it; pass --accept-numerics-drift" in err
    assert not (tmp_path / "pulled" / made.key).exists() and not (tmp_path / "pushed" / made.key).exists()
    assert main(["pull", made.key, source, "--cache", str(tmp_path / "pulled"), "--accept-numerics-drift"]) == 0
    assert "pull goes on (--accept-numerics-drift)" in capsys.readouterr().out
    assert FeatureCache(tmp_path / "pulled" / made.key).complete


# ------------------------------------------------------------------------------------------------ fit
@pytest.fixture(scope="module")
def world(v3_image: Written, tmp_path_factory: pytest.TempPathFactory) -> World:
    """A tiny SmolVLA checkpoint and a timm cache of the same dataset; a fit reads nothing else."""
    return World(tmp_path_factory.mktemp("numerics_fit"), v3_image, encoder=ENCODER,
                 extract_settings={**EXTRACT, "grids": ("4x4",)},
                 fit={"steps": 1, "eval_frames": 2, "num_denoise_steps": 1})


def _cli_fit(world: World, results_file: Path, *flags: str) -> int:
    return main(world.fit_argv(results_file, "--out", str(results_file.parent / "runs"), *flags))


def test_fit_refuses_drift_unless_accepted_and_records_it(world: World, tmp_path: Path, capsys: pytest.CaptureFixture,
                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    nudge(monkeypatch)
    lines: list[str] = []
    with pytest.raises(NumericsError, match=f"^cache {world.encoder_key}: this environment computes different .*"
                                            f"pass --accept-numerics-drift"):
        Fitter(world.request(under=tmp_path), log=lines.append).run()
    assert not (tmp_path / "results.parquet").exists() and not any(": eval_mse " in ln or " as grafted for cell " in ln
                                                                        for ln in lines)  # nothing grafted or scored
    capsys.readouterr()
    assert _cli_fit(world, tmp_path / "r.parquet") == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert err.startswith(f"graftcache fit: error: cache {world.encoder_key}: this environment")
    assert _cli_fit(world, tmp_path / "r.parquet", "--accept-numerics-drift") == 0
    assert f"warning: cache {world.encoder_key}: this environment" in capsys.readouterr().out
    measured = fp.check_numerics(world.encoder_cache)
    assert measured.status == "drift" and measured.drift > fp.TOLERANCE["fp32"]
    (row,) = results.read(tmp_path / "r.parquet").iter_rows(named=True)
    assert row["numerics_drift"] == pytest.approx(measured.drift, rel=1e-3)


def test_fit_in_an_unchanged_environment_records_no_drift(world: World, tmp_path: Path) -> None:
    (row,) = Fitter(world.request(under=tmp_path), log=_quiet).run()
    assert 0 <= row["numerics_drift"] <= fp.TOLERANCE["fp32"]
    assert results.read(tmp_path / "results.parquet")["numerics_drift"].to_list() == [row["numerics_drift"]]


def test_fitters_sharing_verdicts_probe_each_cache_once_and_each_enforces(world: World, tmp_path: Path,
                                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    calls: list[str] = []
    real = run_module.check_numerics
    monkeypatch.setattr(run_module, "check_numerics", lambda cache, **kw: calls.append(cache.key) or real(cache, **kw))
    shared: dict = {}
    Fitter(world.request(under=tmp_path / "a"), log=_quiet, numerics=shared).run()
    Fitter(world.request(under=tmp_path / "b", seeds=(1,)), log=_quiet, numerics=shared).run()
    assert calls == [world.encoder_key] and shared[world.encoder_key].status == "match"
    nudge(monkeypatch)
    drifted = {world.encoder_key: fp.check_numerics(world.encoder_cache)}
    assert drifted[world.encoder_key].status == "drift"
    for folder in ("c", "d"):  # a shared drift verdict is refused by every request that reads the cache
        with pytest.raises(NumericsError, match=f"^cache {world.encoder_key}: this environment computes different"):
            Fitter(world.request(under=tmp_path / folder), log=_quiet, numerics=drifted).run()
    assert calls == [world.encoder_key]


# ------------------------------------------------------------------------------------------------ native towers
def test_smolvla_position_id_drift_is_caught_in_one_line(v3_image: Written, tmp_path: Path,
                                                         capsys: pytest.CaptureFixture) -> None:
    policy = tmp_path / "policy"
    tiny("smolvla").save(policy)
    req = _req(v3_image.root, tmp_path / "cache", encoder=native_name("smolvla"), random_init=False, policy=str(policy))
    with pytest.MonkeyPatch.context() as m:  # the cache is made under transformers 4.57.6's rule and version
        m.setattr(modeling_smolvlm.SmolVLMVisionEmbeddings, "forward", _legacy_position_ids)
        m.setattr(graftcache.extract.provenance, "library_versions",
                  lambda: {**fp.library_versions(), "transformers": "4.57.6"})
        cache = FeatureCache(extract(req, log=_quiet).path)
        assert set(cache.manifest.numerics["outputs"]) == {"grid", "connector"}
        assert fp.check_numerics(cache).status == "match"
    check = fp.check_numerics(cache)  # this environment's transformers, unpatched
    assert check.status == "drift" and check.versions == {"transformers": ("4.57.6", transformers.__version__)}
    line = check.line()
    assert "\n" not in line and line.startswith(f"cache {cache.key}: this environment computes different features")
    assert f"largest probe difference {check.largest:.3g} in the {check.output} output" in line
    assert line.endswith(f"versions differ: transformers 4.57.6 -> {transformers.__version__}")
    assert main(["verify", cache.key, "--cache", str(cache.path.parent), "--numerics"]) == 1
    assert line in capsys.readouterr().out
