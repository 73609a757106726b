"""Released-checkpoint layout at real size: random-init SmolVLA and pi0.5 at the released geometry, saved
as lerobot 0.6 saves a released policy into a Hugging Face cache snapshot, loaded offline by hub id
(as `--policy org/name` does), grafted, and checked where the tiny configurations cannot show anything:
token counts, widths, scaling, pi0.5's hard-coded heads and vocabulary.

SmolVLA (450M) runs a flow step and a prediction here. pi0.5 is 9.4 GB even in bf16 and a flow step
takes ~10 minutes on a CPU, so here it is loaded (graftcache.backbones.lean_load: ~10 GB of memory) and only
its prefix embedding is run (the LM is not); the full step and predict are benchmarks/bench_real_size.py's,
on a GPU.
"""

from __future__ import annotations

import gc
import json
import math
import shutil
from collections.abc import Iterator
from pathlib import Path

import pytest
import torch
from torch import nn

from devtools.released import (
    RANDOM_MARKER,
    build_pi05,
    build_smolvla,
    hub_cache,
    write_random_weights,
)
from graftcache.backbones import load_backbone
from graftcache.backbones.batches import TOKEN_MASK, TOKENS
from graftcache.backbones.checkpoint import state_dict_sha256
from graftcache.backbones.loaded import LoadedBackbones
from graftcache.backbones.tiny_record import resolve_policy
from graftcache.graft import GraftProjector, feature_key

SMOLVLA = "graftcache-tests/smolvla-libero-random"
PI05 = "graftcache-tests/pi05-libero-random"
POLICY_FILES = {"config.json", "model.safetensors", "policy_preprocessor.json", "policy_postprocessor.json",
                RANDOM_MARKER}


@pytest.fixture(scope="module")
def hub(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """One HF hub cache for the module, removed afterwards (pytest keeps old temp dirs; pi0.5 is 9 GB)."""
    cache = tmp_path_factory.mktemp("real_size_hub")
    if shutil.disk_usage(cache).free < 12e9:
        pytest.skip(f"real-size checkpoints need ~11 GB free in {cache}")
    with hub_cache(cache):  # transformers' and lerobot's hub-id lookups, like graftcache's, read this cache
        yield cache
    shutil.rmtree(cache, ignore_errors=True)


@pytest.fixture
def real_hub(hub: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    monkeypatch.setenv("HF_HUB_CACHE", str(hub))  # conftest points every test at the session's cache
    return hub


def _raw(adapter, enc_dim: int, batch: int, seed: int = 0) -> dict:
    g = torch.Generator().manual_seed(seed)
    tokens = adapter.token_grid[0] * adapter.token_grid[1]
    raw = {feature_key(c): torch.randn(batch, tokens, enc_dim, generator=g) for c in adapter.cameras}
    raw["observation.state"] = torch.randn(batch, adapter.state_dim, generator=g) * 0.5
    raw["action"] = torch.randn(batch, adapter.chunk_size, adapter.action_dim, generator=g) * 0.5
    raw["action_is_pad"] = torch.zeros(batch, adapter.chunk_size, dtype=torch.bool)
    raw["task"] = ["put the black bowl on the plate"] * batch
    return raw


def _assert_released_layout(snapshot: Path, repo_id: str) -> None:
    repo = snapshot.parents[1]
    assert repo.name == f"models--{repo_id.replace('/', '--')}"
    assert (repo / "refs" / "main").read_text() == snapshot.name
    assert POLICY_FILES <= {p.name for p in snapshot.iterdir()}
    assert all(p.is_symlink() and p.resolve().parent == repo / "blobs" for p in snapshot.iterdir())
    assert json.loads((snapshot / RANDOM_MARKER).read_text())["random_init"] is True


@pytest.mark.slow
def test_smolvla_released_layout_loads_by_hub_id_and_grafts_at_real_geometry(real_hub: Path) -> None:
    _assert_released_layout(build_smolvla(SMOLVLA, cache=real_hub), SMOLVLA)
    # the CLI's path: `--policy org/name` passes through resolve_policy to the loaded backbones (load_backbone)
    source = resolve_policy("smolvla", SMOLVLA, identity={}, root=real_hub)
    assert source == SMOLVLA
    adapter = LoadedBackbones().get("smolvla", source, "cpu")
    assert adapter.random_init and adapter.source == SMOLVLA  # recorded as random weights, not a release

    vlm = adapter.policy.model.vlm_with_expert.get_vlm_model().config
    assert (vlm.text_config.hidden_size, vlm.vision_config.image_size, vlm.scale_factor) == (960, 512, 4)
    assert adapter.token_grid == (8, 8) and adapter.lm_width == 960 and adapter.embed_scale == math.sqrt(960)
    assert adapter.cameras == ("image", "image2") and (adapter.chunk_size, adapter.action_dim) == (50, 7)

    torch.manual_seed(0)
    adapter.graft(GraftProjector(384, adapter.lm_width))
    raw = _raw(adapter, 384, batch=2)
    batch = adapter.prepare(raw)
    policy = adapter.policy
    with torch.no_grad():  # lerobot's own prefix: per camera 64 image tokens x 960, scaled by sqrt(960)
        images, masks = policy.prepare_images(batch)
        embs, pad, _ = policy.model.embed_prefix(images, masks, batch[TOKENS], batch[TOKEN_MASK],
                                                 policy.prepare_state(batch))
        for i, camera in enumerate(adapter.cameras):
            expected = adapter.projector(raw[feature_key(camera)]) * math.sqrt(960)
            torch.testing.assert_close(embs[:, 64 * i: 64 * (i + 1)], expected)
    assert embs.shape[-1] == 960 and pad[:, :128].all()

    policy.train()
    loss = adapter.loss(batch)
    assert loss.shape == (2,) and torch.isfinite(loss).all()
    loss.mean().backward()
    with_grad = {n for n, p in policy.named_parameters() if p.grad is not None}
    connector = "model.vlm_with_expert.vlm.model.connector"
    assert with_grad == {f"{connector}.{n}" for n, _ in adapter.projector.named_parameters()}
    chunk = adapter.predict(batch, adapter.sample_noise(2, torch.Generator().manual_seed(1)), num_steps=2)
    assert chunk.shape == (2, 50, 7) and torch.isfinite(chunk).all()


@pytest.mark.slow
def test_pi05_released_layout_loads_by_hub_id_at_real_geometry(real_hub: Path) -> None:
    gc.collect()  # a grafted adapter and its policy are a cycle: free the SmolVLA test's before 9 GB more
    snapshot = build_pi05(PI05, cache=real_hub)
    _assert_released_layout(snapshot, PI05)
    adapter = load_backbone("pi05", PI05)  # config, processors, tokenizer, lean weights load: the real path
    assert adapter.random_init and adapter.source == PI05
    # materialised in the config's dtypes (bf16 LM and expert; vision path, norms, adaRMS fp32) and no more
    params = dict(adapter.policy.named_parameters())
    assert params["model.paligemma_with_expert.paligemma.model.language_model.layers.0.mlp.up_proj.weight"].dtype \
        == torch.bfloat16
    assert params["model.paligemma_with_expert.paligemma.model.multi_modal_projector.linear.weight"].dtype \
        == torch.float32
    assert not any(t.is_meta for t in (*params.values(), *adapter.policy.buffers()))
    tensors = {id(t): t for t in adapter.policy.state_dict(keep_vars=True).values()}  # tied weights once
    storages = {t.untyped_storage().data_ptr(): t.untyped_storage().nbytes() for t in tensors.values()}
    held = sum(storages.values())  # no tensor is a view into a larger buffer (the file, a staging buffer):
    assert held == sum(t.numel() * t.element_size() for t in tensors.values())
    # the file's size, but for the action/time projections the builder writes in bf16 and lerobot makes fp32
    assert held <= 1.001 * (snapshot / "model.safetensors").stat().st_size
    paligemma = adapter.policy.model.paligemma_with_expert.paligemma.model  # lerobot's own PaliGemmaModel
    text = paligemma.config.text_config
    assert (text.num_attention_heads, text.num_key_value_heads, text.head_dim) == (8, 1, 256)
    assert (text.hidden_size, text.num_hidden_layers, text.vocab_size) == (2048, 18, 257152)
    assert paligemma.language_model.embed_tokens.weight.shape == (257152, 2048)
    assert adapter.token_grid == (16, 16) and adapter.lm_width == 2048 and adapter.embed_scale == 1.0
    assert list(adapter.config.image_features) == [
        "observation.images.image", "observation.images.image2", "observation.images.empty_camera_0"]

    torch.manual_seed(0)
    adapter.graft(GraftProjector(1152, adapter.lm_width))
    raw = _raw(adapter, 1152, batch=1)
    del raw["action"], raw["action_is_pad"]
    batch = adapter.prepare(raw)
    # lerobot's own prefix: 3 slots x 256 tokens x 2048, the empty one masked, no scaling (the LM is not run)
    with torch.no_grad():
        images, masks = adapter.policy._preprocess_images(batch)
        embs, pad, _ = adapter.policy.model.embed_prefix(images, masks, batch[TOKENS], batch[TOKEN_MASK])
        for i, camera in enumerate(adapter.cameras):
            expected = adapter.projector(raw[feature_key(camera)])
            torch.testing.assert_close(embs[:, 256 * i: 256 * (i + 1)].float(), expected)
    assert embs.shape == (1, 3 * 256 + adapter.config.tokenizer_max_length, 2048)
    assert pad[0, :768].view(3, 256).all(dim=1).tolist() == [True, True, False]
    assert not pad[0, 512:768].any()
    adapter.reset()  # the graft wrote no weight and kept no copy: the policy hashes as loaded
    assert state_dict_sha256(adapter.policy) == adapter.policy_sha256


def test_random_weights_are_written_as_safetensors_saves_them(tmp_path: Path) -> None:
    """Module-by-module writing from the meta device gives the file `save_model` gives (keys, dtypes,
    shapes, loadable strictly), deterministic for a seed."""
    from safetensors import safe_open
    from safetensors.torch import load_file, save_model

    def model() -> nn.Module:
        net = nn.Sequential(nn.Linear(5, 3), nn.LayerNorm(3), nn.Linear(3, 7))
        net[2].to(torch.bfloat16)
        return net

    with torch.device("meta"):
        meta = model()
    write_random_weights(meta, tmp_path / "a.safetensors", seed=3)
    write_random_weights(meta, tmp_path / "b.safetensors", seed=3)
    save_model(model(), str(tmp_path / "ref.safetensors"))
    assert (tmp_path / "a.safetensors").read_bytes() == (tmp_path / "b.safetensors").read_bytes()

    def header(path: Path) -> dict:
        with safe_open(str(path), framework="pt") as f:
            return {k: (f.get_slice(k).get_dtype(), tuple(f.get_slice(k).get_shape())) for k in f.keys()}

    assert header(tmp_path / "a.safetensors") == header(tmp_path / "ref.safetensors")
    loaded = model()
    loaded.load_state_dict(load_file(tmp_path / "a.safetensors"), strict=True)
    assert torch.equal(loaded[1].weight, torch.ones(3)) and loaded[0].weight.abs().max() <= 1 / math.sqrt(5)
