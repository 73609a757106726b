"""The `align` objective's closed-form ridge: recovers a known linear map through the projector."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from graftcache.errors import FitError
from graftcache.fit.align import fit_ridge
from graftcache.graft import GraftProjector


def test_ridge_recovers_a_known_projection_on_every_camera() -> None:
    g = torch.Generator().manual_seed(0)
    c, d = 24, 10
    w, b = torch.randn(c, d, generator=g), torch.randn(d, generator=g)
    sources = [torch.randn(300, 4, c, generator=g) * 3 + 1 for _ in range(2)]  # two cameras, 2x2 grids
    targets = [F.layer_norm(s, (c,)) @ w + b for s in sources]
    projector = GraftProjector(c, d)
    # streamed in chunks of 100 frames, as a fit feeds it
    pairs = [(s[i:i + 100], t[i:i + 100]) for s, t in zip(sources, targets, strict=True) for i in range(0, 300, 100)]
    r2 = fit_ridge(projector, pairs, (2, 2), alpha=1e-8)
    assert r2 == pytest.approx(1.0, abs=1e-6)
    with torch.no_grad():
        for s, t in zip(sources, targets, strict=True):
            torch.testing.assert_close(projector(s), t, atol=1e-3, rtol=1e-3)


def test_ridge_pools_finer_native_tokens_and_reports_partial_fit() -> None:
    g = torch.Generator().manual_seed(1)
    src = torch.randn(200, 4, 8, generator=g)
    native = torch.randn(200, 16, 5, generator=g)  # the tower's 4x4 grid, pooled to the graft's 2x2
    r2 = fit_ridge(GraftProjector(8, 5), [(src, native)], (2, 2))
    assert 0.0 <= r2 < 0.2  # unrelated noise: little variance explained
    with pytest.raises(FitError, match="do not line up"):
        fit_ridge(GraftProjector(8, 5), [(src[:100], native)], (2, 2))


def test_ridge_on_features_that_never_vary_gives_the_mean_target() -> None:
    """The zero-image control feeds zeros: no spread to scale the ridge by. Least squares then says W = 0 and b = the
    mean target (once a singular solve)."""
    g = torch.Generator().manual_seed(1)
    targets = torch.randn(50, 4, 6, generator=g)
    projector = GraftProjector(8, 6)
    r2 = fit_ridge(projector, [(torch.zeros(50, 4, 8), targets)], (2, 2))
    assert r2 == pytest.approx(0.0, abs=1e-6)
    with torch.no_grad():
        torch.testing.assert_close(projector.proj.weight, torch.zeros(6, 8))
        torch.testing.assert_close(projector(torch.zeros(3, 4, 8)), targets.reshape(-1, 6).mean(0).expand(3, 4, 6),
                                   atol=1e-5, rtol=1e-5)
