"""Stage 2's streamed data path on synthetic caches (seeded random features written by the store's own writer):
blocks, their order across epochs and worker counts, the shuffle buffer, the shuffled-image pairing, NaN checks
in workers, and scoring from a stream against a computation written here."""

from __future__ import annotations

import pickle
from collections.abc import Iterator
from contextlib import closing
from itertools import islice
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers.backbones import tiny
from helpers.caches import CAMERAS, synthetic_cache

from graftcache.errors import FitError
from graftcache.fit.buffer import ShuffleBuffer, buffer_frames
from graftcache.fit.controls import SHUFFLE_GROUP, shuffle
from graftcache.fit.data import LowDim, load_lowdim
from graftcache.fit.feed import SplitFeed
from graftcache.fit.loop import evaluate
from graftcache.fit.stream import Block, BlockMemo, FeatureSource, StreamStats, read_blocks
from graftcache.graft import GraftProjector, feature_key
from graftcache.nonfinite import nonfinite_rows
from graftcache.scoring import frame_noise
from graftcache.store import FeatureCache

BLOCK = 8
LENGTHS = (13, 9, 11, 7, 10, 12, 30, 25)  # 117 frames in 15 blocks of 8
EVAL_BATCH_SIZE = 64  # 67 scored frames: 2 batches


@pytest.fixture(scope="module")
def cache(tmp_path_factory: pytest.TempPathFactory) -> FeatureCache:
    return synthetic_cache(tmp_path_factory.mktemp("stream") / "k", LENGTHS, block_frames=BLOCK)


def _pooled(cache: FeatureCache, rows: np.ndarray, camera: str) -> torch.Tensor:
    """The stored 4x4 features of `rows` averaged over 2x2 cells (the 2x2 grid), straight from zarr."""
    stored = torch.from_numpy(cache.group[f"features/{camera}/4x4"][...][rows]).float()
    cells = stored.reshape(len(rows), 2, 2, 2, 2, -1)  # [n, out_h, in_h, out_w, in_w, C]
    return cells.mean(dim=(2, 4)).reshape(len(rows), 4, -1).half()


def _blocks(stream, workers: int, n: int | None = None, stats: StreamStats | None = None) -> list[Block]:
    with closing(read_blocks(stream, workers, stats)) as blocks:
        return list(islice(blocks, n) if n is not None else blocks)


def test_every_frame_once_per_epoch_in_one_order_for_any_worker_count(cache: FeatureCache) -> None:
    low = load_lowdim(cache, "libero_spatial", chunk=5).subset([0, 2, 3, 5, 6, 7])
    feed = SplitFeed(low, FeatureSource.of(cache, CAMERAS, (2, 2)), BLOCK)
    n = feed.n_blocks
    runs = {w: _blocks(feed.features(seed=3), w, 2 * n) for w in (0, 1, 2)}
    epochs = [np.concatenate([c.owners for c in runs[0][e * n:(e + 1) * n]]) for e in (0, 1)]
    for owners in epochs:
        assert sorted(owners) == list(range(len(low)))  # every train frame exactly once per epoch
    assert not np.array_equal(epochs[0], epochs[1])  # the next epoch has its own order
    for block in runs[0]:
        assert len(np.unique(low.rows[block.owners] // BLOCK)) == 1  # each Block lies in one cache block
        for camera in CAMERAS:  # pooled to 2x2 in the worker, as read_grid pools
            torch.testing.assert_close(block.features[0][camera], _pooled(cache, low.rows[block.owners], camera))
    for w in (1, 2):  # the same blocks in the same order, bit for bit, whatever reads them
        assert len(runs[w]) == len(runs[0])
        for a, b in zip(runs[0], runs[w], strict=True):
            assert np.array_equal(a.owners, b.owners)
            assert all(torch.equal(a.features[0][c], b.features[0][c]) for c in CAMERAS)
    assert np.array_equal(np.concatenate([c.owners for c in _blocks(feed.features(seed=None), 2)]),
                          np.arange(len(low)))  # unshuffled: once, in cache order


def test_shuffle_buffer_holds_its_capacity_and_draws_each_frame_once(cache: FeatureCache) -> None:
    low = load_lowdim(cache, "libero_spatial", chunk=5)
    feed = SplitFeed(low, FeatureSource.of(cache, CAMERAS, (4, 4)), BLOCK)
    delivered: list[np.ndarray] = []

    def tapped(blocks: Iterator[Block]) -> Iterator[Block]:
        for block in blocks:
            delivered.append(block.owners)
            yield block

    capacity, k, draws = 20, 6, 30  # 200 frames drawn: more than an epoch (117)
    g = torch.Generator().manual_seed(0)
    stored = {c: torch.from_numpy(cache.group[f"features/{c}/4x4"][...]) for c in CAMERAS}
    with closing(read_blocks(feed.features(seed=1), 0)) as blocks:
        buffer = ShuffleBuffer(tapped(blocks), capacity)
        drawn = []
        for _ in range(draws):
            owners, features = buffer.draw(k, g)
            assert len(set(owners.tolist())) == k
            for c in CAMERAS:  # each slot's features are its frame's
                assert torch.equal(features[c], stored[c][torch.from_numpy(low.rows[owners])])
            drawn.append(owners)
        assert all(v.shape[0] == capacity for v in buffer._features.values())
        held = buffer._owners.copy()
    stream = np.concatenate(delivered)
    used = capacity + draws * k  # what the buffer took from the stream: its fill, then one frame per frame drawn
    assert len(stream) - used < BLOCK  # it read ahead by less than one block
    assert sorted(np.concatenate([*drawn, held]).tolist()) == sorted(stream[:used].tolist())
    first = np.concatenate(drawn)[:len(low) - capacity]
    assert len(set(first.tolist())) == len(first)  # no frame drawn twice before the epoch is through
    with closing(read_blocks(feed.features(seed=1), 0)) as blocks, pytest.raises(FitError, match="batch of 21"):
        ShuffleBuffer(blocks, capacity).draw(21, g)


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16, torch.float32, torch.float64])
def test_nonfinite_rows_read_from_the_bits_agree_with_isfinite(dtype: torch.dtype) -> None:
    x = torch.randn(40, 3, 5).to(dtype) * 100
    x[3, 1, 2], x[7, 0, 0], x[9, 2, 4] = float("nan"), float("inf"), -float("inf")
    x[11, 0, 0], x[12, 2, 1], x[13, 1, 1] = torch.finfo(dtype).max, -torch.finfo(dtype).max, torch.finfo(dtype).tiny
    want = (~torch.isfinite(x)).reshape(40, -1).any(1).numpy()
    assert want.sum() == 3 and np.array_equal(nonfinite_rows(x), want)
    if dtype != torch.bfloat16:  # numpy has no bfloat16
        assert np.array_equal(nonfinite_rows(x.numpy()), want)


def test_buffer_size_comes_from_mib_within_one_batch_and_the_split() -> None:
    assert buffer_frames(1, 1 << 16, 4, 100) == 16           # 1 MiB of 64 KiB frames
    assert buffer_frames(1, 3 << 20, 4, 100) == 4            # at least one batch
    assert buffer_frames(1000, 10, 4, 50) == 50              # at most the split


@pytest.mark.parametrize("n", [2, 3, 5, 63, 64, 65, 127, 128, 129, 300, 1000])
def test_shuffled_image_pairing_is_a_permutation_without_fixed_points(n: int) -> None:
    for seed in range(20):
        pairing = shuffle(n, seed)
        assert sorted(pairing.tolist()) == list(range(n)), (n, seed)
        assert not (pairing == np.arange(n)).any(), (n, seed)
        assert np.array_equal(pairing, shuffle(n, seed))
    assert len({tuple(shuffle(n, seed)) for seed in range(20)}) > 1 or n == 2  # the seed picks the pairing
    groups = max(1, n // SHUFFLE_GROUP) - 1
    for group in range(groups):  # a group's frames see one other group's frames (when there are two or more)
        seen = pairing[group * SHUFFLE_GROUP:(group + 1) * SHUFFLE_GROUP] // SHUFFLE_GROUP
        assert len(set(seen.tolist())) == 1 and (seen[0] != group or groups == 1)


def test_a_pairing_hands_each_frame_the_features_of_its_partner(cache: FeatureCache) -> None:
    low = load_lowdim(cache, "libero_spatial", chunk=5)
    pairing = shuffle(len(low), 4)
    feed = SplitFeed(low, FeatureSource.of(cache, CAMERAS, (4, 4)), BLOCK, pairing=pairing)
    blocks = _blocks(feed.features(seed=None), 2)
    assert sorted(np.concatenate([c.owners for c in blocks]).tolist()) == list(range(len(low)))
    for block in blocks:
        want = torch.from_numpy(cache.group["features/image/4x4"][...][low.rows[pairing[block.owners]]])
        assert torch.equal(block.features[0]["image"], want)


def test_nan_features_are_refused_by_name_from_a_worker_or_dropped_and_counted(tmp_path: Path) -> None:
    nan = synthetic_cache(tmp_path / "nan", LENGTHS, block_frames=BLOCK, nan_at=(2, 3))
    low = load_lowdim(nan, "libero_spatial", chunk=5)
    source = FeatureSource.of(nan, CAMERAS, (4, 4))
    with pytest.raises(FitError) as refused:
        _blocks(SplitFeed(low, source, BLOCK).features(seed=None), 2)
    message = str(refused.value)
    assert "\n" not in message and "Traceback" not in message
    for text in (f"cache {nan.key}", "features/image", "episode 2 frame 3", "--drop-nonfinite"):
        assert text in message
    stats = StreamStats()
    kept = _blocks(SplitFeed(low, source, BLOCK, drop=True).features(seed=None), 2, stats=stats)
    row = int(np.flatnonzero((low.episode_index == 2) & (low.frame_index == 3))[0])
    assert stats.dropped == {int(low.rows[row])}
    assert sorted(np.concatenate([c.owners for c in kept]).tolist()) == sorted(set(range(len(low))) - {row})


def _chunk_reference(low: LowDim, pos: np.ndarray, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Action chunks written out frame by frame: the next `chunk` actions of the episode, the last repeated."""
    chunks, pad = [], []
    for p in pos:
        ep_actions = actions[low.stream_start[p] - low.frame_index[p]:low.stream_end[p]]
        steps = [low.frame_index[p] + i for i in range(low.chunk)]
        chunks.append([ep_actions[min(s, len(ep_actions) - 1)] for s in steps])
        pad.append([s >= len(ep_actions) for s in steps])
    return np.asarray(chunks), np.asarray(pad)


@pytest.mark.usefixtures("one_torch_thread")
def test_streamed_scoring_equals_scoring_written_out_here(cache: FeatureCache) -> None:
    adapter = tiny("smolvla")
    torch.manual_seed(0)
    adapter.graft(GraftProjector(8, adapter.lm_width))
    low = load_lowdim(cache, "libero_spatial", chunk=adapter.chunk_size).subset([5, 6, 7])  # 67 frames: 2 batches
    cams = {c: c for c in adapter.cameras}  # CAMERAS are the tiny policy's cameras
    feed = SplitFeed(low, FeatureSource.of(cache, CAMERAS, (4, 4)), BLOCK)
    score = evaluate(adapter, low, read_blocks(feed.features(seed=None), 2), cams, batch_size=EVAL_BATCH_SIZE,
                     num_denoise_steps=2)

    adapter.policy.eval()
    stored = {c: torch.from_numpy(cache.group[f"features/{c}/4x4"][...]).float() for c in CAMERAS}
    actions = cache.group["action_stream/action"][...]
    chunks, pad = _chunk_reference(low, np.arange(len(low)), actions)
    preds, targets = [], []
    with torch.no_grad():
        for s in range(0, len(low), EVAL_BATCH_SIZE):
            pos = np.arange(s, min(s + EVAL_BATCH_SIZE, len(low)))
            raw = {feature_key(k): stored[c][torch.from_numpy(low.rows[pos])] for k, c in cams.items()}
            raw.update({"observation.state": low.state[pos], "task": [low.tasks[int(t)] for t in low.task_index[pos]],
                        "action": torch.from_numpy(chunks[pos]), "action_is_pad": torch.from_numpy(pad[pos])})
            batch = adapter.prepare(raw)
            noise = frame_noise(low.rows[pos], adapter.chunk_size, adapter.max_action_dim)
            preds.append(adapter.predict(batch, noise=noise, num_steps=2).numpy())
            targets.append(batch["action"].numpy())
    pred, target = np.concatenate(preds).astype(np.float64), np.concatenate(targets).astype(np.float64)
    valid = ~pad
    per_frame = (((pred - target) ** 2).mean(-1) * valid).sum(-1) / valid.sum(-1)
    pred_raw = adapter.unnormalize(torch.from_numpy(np.concatenate(preds))).numpy().astype(np.float64)
    raw_mse = ((((pred_raw - chunks) ** 2).mean(-1) * valid).sum(-1) / valid.sum(-1)).mean()
    assert score.n_frames == len(low)
    assert score.mse == pytest.approx(per_frame.mean(), rel=1e-5)
    assert score.mse_first == pytest.approx(((pred[:, 0] - target[:, 0]) ** 2).mean(), rel=1e-5)
    assert score.mse_raw == pytest.approx(raw_mse, rel=1e-5)
    for part, dims in ((score.mse_arm, slice(0, -1)), (score.mse_gripper, slice(-1, None))):  # arm: all but the last
        err = ((pred[..., dims] - target[..., dims]) ** 2).mean(-1)
        assert part == pytest.approx(((err * valid).sum(-1) / valid.sum(-1)).mean(), rel=1e-5)
    for episode in np.unique(low.episode_index):
        assert score.per_episode[int(episode)] == pytest.approx(per_frame[low.episode_index == episode].mean(),
                                                                 rel=1e-5)


def test_a_memo_reads_each_block_once_returns_the_direct_values_and_keeps_to_its_budget(
        cache: FeatureCache, monkeypatch: pytest.MonkeyPatch) -> None:
    source = FeatureSource.of(cache, CAMERAS, (2, 2))
    reads: list[tuple[str, list[int]]] = []
    direct = FeatureSource.read_camera
    monkeypatch.setattr(FeatureSource, "read_camera",
                        lambda self, camera, rows: reads.append((camera, rows.tolist())) or direct(self, camera, rows))
    rows = np.array([17, 3, 40, 5, 18, 41])  # blocks 2, 0, 5, 0, 2, 5: out of order, repeated
    tokens, width = source.frame_shape(CAMERAS[0])
    block_bytes = BLOCK * tokens * width * 2  # fp16

    memo = BlockMemo(budget=1 << 20)
    kept = memo.read(source, rows)
    whole = [list(range(b * BLOCK, (b + 1) * BLOCK)) for b in (0, 2, 5)]
    assert reads == [(c, r) for c in CAMERAS for r in whole]  # each camera's blocks, whole, once
    assert memo.nbytes == 3 * len(CAMERAS) * block_bytes
    for camera in CAMERAS:
        assert torch.equal(kept[camera], direct(source, camera, rows))  # bit for bit what streaming reads
        torch.testing.assert_close(kept[camera], _pooled(cache, rows, camera))
    reads.clear()
    again = memo.read(source, np.array([23, 0, 16]))
    assert reads == []  # blocks 2 and 0 were kept
    assert all(torch.equal(again[c], direct(source, c, np.array([23, 0, 16]))) for c in CAMERAS)

    one = BlockMemo(budget=block_bytes)  # room for one block: the least recently used goes
    values = one.read(source, rows)
    assert one.nbytes == block_bytes
    assert all(torch.equal(values[c], kept[c]) for c in CAMERAS)

    reads.clear()
    none = BlockMemo(budget=block_bytes - 1)  # a block it could never keep: read as asked, nothing kept
    values = none.read(source, rows)
    assert reads == [(c, rows.tolist()) for c in CAMERAS] and none.nbytes == 0
    assert all(torch.equal(values[c], kept[c]) for c in CAMERAS)


def test_a_memo_never_travels_to_a_worker(cache: FeatureCache) -> None:
    low = load_lowdim(cache, "libero_spatial", chunk=5)
    memo = BlockMemo(budget=1 << 20)
    stream = SplitFeed(low, FeatureSource.of(cache, CAMERAS, (2, 2)), BLOCK, memo=memo).features(seed=0)
    assert stream.memo is memo and pickle.loads(pickle.dumps(stream)).memo is None
    first = _blocks(stream, 0, 3)
    kept = memo.nbytes
    assert kept > 0  # read in this process: kept
    second = _blocks(stream, 2, 6)  # read by workers: the same blocks, and the next ones are not kept here
    assert memo.nbytes == kept
    assert all(torch.equal(a.features[0][c], b.features[0][c]) for a, b in zip(first, second[:3], strict=True)
               for c in CAMERAS)
