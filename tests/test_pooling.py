"""pool_grid against hand-written block means; grid-string parsing, `unpooled` included."""

from __future__ import annotations

import pytest
import torch

from graftcache.errors import GraftcacheError
from graftcache.pooling import format_grid, grid_names, parse_grids, pool_grid, resolve_grids
from graftcache.requests import ExtractRequest


def _block_mean(grid: torch.Tensor, out: tuple[int, int]) -> torch.Tensor:
    """Reference: token (i, j) = mean of the (H/h x W/w) block at row i, column j, row-major."""
    b, h, w, c = grid.shape
    bh, bw = h // out[0], w // out[1]
    tokens = []
    for i in range(out[0]):
        for j in range(out[1]):
            tokens.append(grid[:, i * bh:(i + 1) * bh, j * bw:(j + 1) * bw, :].mean(dim=(1, 2)))
    return torch.stack(tokens, dim=1)


@pytest.mark.parametrize(("unpooled", "out"), [((16, 16), (8, 8)), ((16, 16), (4, 4)), ((14, 14), (7, 7)),
                                             ((8, 8), (8, 8)), ((16, 8), (4, 2)), ((18, 18), (6, 3))])
def test_pool_grid_is_block_mean(unpooled: tuple[int, int], out: tuple[int, int]) -> None:
    grid = torch.randn(3, *unpooled, 5, generator=torch.Generator().manual_seed(0))
    pooled = pool_grid(grid, out)
    assert pooled.shape == (3, out[0] * out[1], 5)
    torch.testing.assert_close(pooled, _block_mean(grid, out), rtol=1e-5, atol=1e-6)


def test_pool_grid_to_its_own_size_is_unchanged_and_row_major() -> None:
    grid = torch.arange(2 * 3 * 4 * 1, dtype=torch.float32).reshape(2, 3, 4, 1)
    tokens = pool_grid(grid, (3, 4))
    assert torch.equal(tokens[:, :, 0], grid[..., 0].reshape(2, 12))
    assert tokens[0, 5, 0] == grid[0, 1, 1, 0]  # token i*w + j is cell (i, j)


def test_pooling_past_the_unpooled_grid_repeats_cells() -> None:
    grid = torch.randn(1, 8, 8, 4)
    up = pool_grid(grid, (16, 16)).reshape(1, 16, 16, 4)
    assert torch.equal(up, grid.repeat_interleave(2, dim=1).repeat_interleave(2, dim=2))


def test_pool_grid_rejects_non_grid() -> None:
    with pytest.raises(GraftcacheError, match=r"\[B,H,W,C\]"):
        pool_grid(torch.zeros(2, 64, 8), (4, 4))


def test_parse_grids() -> None:
    assert parse_grids("8x8,16x16") == [(8, 8), (16, 16)]
    assert parse_grids(" 4x2 , 8x8,4x2") == [(4, 2), (8, 8)]
    assert [format_grid(g) for g in parse_grids("16x16,8x8")] == ["16x16", "8x8"]


@pytest.mark.parametrize("text", ["", "8", "8x", "0x8", "8x8,", "axb", "8x8;16x16", "-1x4"])
def test_parse_grids_rejects(text: str) -> None:
    with pytest.raises(GraftcacheError, match="expected HxW"):
        parse_grids(text)


def test_grid_names_resolve_unpooled_to_the_encoders_grid() -> None:
    assert grid_names(" unpooled, 4 x 4,4x4,unpooled") == ("unpooled", "4x4")
    assert resolve_grids(("unpooled",), (16, 16)) == [(16, 16)]
    assert resolve_grids(("unpooled", "16x16", "4x4"), (16, 16)) == resolve_grids(("16x16", "4x4"), (16, 16)) \
        == [(16, 16), (4, 4)]
    assert resolve_grids(("4x4", "unpooled"), (8, 8)) == [(4, 4), (8, 8)]
    with pytest.raises(GraftcacheError, match="grid 'natve' in 'natve,4x4': expected unpooled"):
        grid_names("natve,4x4")
    with pytest.raises(GraftcacheError, match="expected HxW"):  # a pool-HxW control has no unpooled spelling
        parse_grids("unpooled")


@pytest.mark.parametrize("grids", [(), ("4y4",), ("unpooled", ""), ((4, 4),)])
def test_extract_request_refuses_what_names_no_grid(grids: tuple) -> None:
    with pytest.raises(GraftcacheError, match=r"grids = .* must name grids: unpooled or HxW"):
        ExtractRequest(dataset="d", encoder="e", grids=grids)
