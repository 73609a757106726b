"""train-tiny's recipe: what `state_dropout` feeds the policy, and that recipes from before it keep their keys."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from graftcache import pretrain
from graftcache.requests import TinyTrainConfig

SAMPLE = Path(__file__).resolve().parents[1] / "data" / "libero_sample"


class _Drawn(Exception):
    """Raised by the stand-in optimiser once it has the batches: nothing is trained."""


def _batches(monkeypatch: pytest.MonkeyPatch, tmp_path: Path, cfg: TinyTrainConfig) -> list[dict]:
    def capture(adapter, draw, *, generator, **_):
        raise _Drawn([draw(generator) for _ in range(4)])

    monkeypatch.setattr(pretrain, "optimise", capture)
    with pytest.raises(_Drawn) as drawn:
        pretrain.train_tiny("pi05", str(SAMPLE), cfg=cfg, cache=str(tmp_path), out=tmp_path / "policy")
    return drawn.value.args[0]


def test_state_dropout_feeds_the_mean_state_to_its_share_of_samples(monkeypatch: pytest.MonkeyPatch,
                                                                   tmp_path: Path) -> None:
    _, _, table = pretrain._decode_all(str(SAMPLE), ("image", "image2"), 128, lambda _: None)
    states = torch.from_numpy(np.stack(table["state"].to_numpy()).astype(np.float32))
    mean = states.mean(0)

    def is_mean(batch: dict) -> torch.Tensor:
        return (batch["observation.state"] == mean).all(1)

    def is_a_frame(batch: dict) -> torch.Tensor:
        return (batch["observation.state"][:, None] == states[None]).all(2).any(1)

    kept = _batches(monkeypatch, tmp_path, TinyTrainConfig(batch_size=64, state_dropout=0.0))
    assert all(is_a_frame(b).all() and not is_mean(b).any() for b in kept)
    half = _batches(monkeypatch, tmp_path, TinyTrainConfig(batch_size=64, state_dropout=0.5))
    dropped = torch.cat([is_mean(b) for b in half])
    assert 0.35 < dropped.float().mean() < 0.65
    assert torch.cat([is_a_frame(b) for b in half]).eq(~dropped).all()  # the others read their frame's state
    # the images and actions of a batch are those of the frames drawn, whatever the state shows
    torch.testing.assert_close(half[0]["action"], kept[0]["action"])

def test_recipes_from_before_state_dropout_keep_their_keys() -> None:
    assert "state_dropout" not in TinyTrainConfig().as_dict("smolvla")
    assert TinyTrainConfig(state_dropout=0.5).as_dict("smolvla")["state_dropout"] == 0.5
