"""One backbone pass of several cells (`fit --cells-per-pass`, graftcache.graft.FusedProjector): for every
backbone in the table, two projectors fused over a batch of two samples give each sample the loss its own
projector gives it alone, or the backbone is kept out of fused passes (`per_sample_loss` False)."""

from __future__ import annotations

import pytest
import torch
from helpers.backbones import ENC_DIM, fixed_noise_time, raw_features, tiny

from graftcache.backbone_table import BACKBONES
from graftcache.graft import FusedProjector, GraftProjector


@pytest.mark.parametrize("name", sorted(BACKBONES))
def test_a_fused_pass_equals_each_projector_alone(name: str) -> None:
    adapter = tiny(name)
    if not adapter.per_sample_loss:  # graftcache.fit.run.Fitter.pass_key runs its cells alone
        pytest.skip(f"{name}: one loss a batch, cells never share a pass")
    adapter.policy.eval()  # no dropout (tiny X-VLA's): its draws for a batch of two are not those for one sample
    torch.manual_seed(0)
    members = [GraftProjector(ENC_DIM, adapter.lm_width) for _ in range(2)]
    raw = raw_features(adapter, 2)
    noise, time = fixed_noise_time(adapter, 2)
    alone = []
    for i, projector in enumerate(members):
        adapter.graft(projector)
        one = {k: v[i:i + 1] for k, v in raw.items()}
        with torch.no_grad():
            alone.append(adapter.loss(adapter.prepare(one), noise[i:i + 1], time[i:i + 1]))
        adapter.reset()
    fused = FusedProjector(members)
    adapter.graft(fused)
    with torch.no_grad(), fused.rows([1, 1]):
        together = adapter.loss(adapter.prepare(raw), noise, time)
    torch.testing.assert_close(together, torch.cat(alone))
