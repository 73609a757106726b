"""What the adapters grafting Qwen-VL-style towers at a prompt's image pads share (EO-1, Wall-X, GR00T, VLA-JEPA).

Each of them builds its prompt from blank frames whose processed grid is the cached features' grid, swaps Qwen's
`pixel_values` for those features, and has Qwen's image step run them through the pass-through and the projector.
The policy-specific parts (which processor, which step, where the pads go) stay in the adapters; the checks and
the arithmetic that are the same for all of them live here, once, so their one-line errors read the same.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import torch
from torch import nn

from graftcache.backbones.batches import STATE
from graftcache.errors import BackboneError
from graftcache.graft import feature_key


class TowerReads:
    """Mixin for an adapter whose `_vision(images)` runs its policy's own processor and ViT once and returns both
    native reads, (pre-merger patch grid [B, gh, gw, C] in raster order, post-merger tokens [B, T, D]): a method
    pair, so a mixin rather than a function (placed before BackboneAdapter, whose defaults it overrides)."""

    @torch.no_grad()
    def native_patch_grid(self, images: torch.Tensor) -> torch.Tensor:
        """The ViT's last block before the merger, [B, gh, gw, C] at patch resolution (2x the merged grid)."""
        return self._vision(images)[0]

    @torch.no_grad()
    def native_tokens(self, images: torch.Tensor) -> torch.Tensor:
        """Post-merger tokens [B, gh/2 * gw/2, D], in the order the policy scatters them into the prompt."""
        return self._vision(images)[1]


def tied_head_keys(file_keys: Iterable[str], head: str, embed: str) -> dict[str, str]:
    """{policy key: checkpoint key} for a policy whose LM head is tied to its word embedding: safetensors keeps
    one of the two names, the other is read from it."""
    keys = {k: k for k in file_keys}
    for a, b in ((head, embed), (embed, head)):
        if a in keys and b not in keys:
            keys[b] = keys[a]
    return keys


def merged_grid(size: tuple[int, int], patch: int, merge: int, min_pixels: int | None = None,
                max_pixels: int | None = None) -> tuple[int, int]:
    """The merged token grid Qwen's image processor gives an image of `size`: smart_resize to multiples of
    patch x merge within the pixel bounds (transformers' defaults where None), then one token per merge block."""
    from transformers.models.qwen2_vl.image_processing_qwen2_vl import smart_resize

    factor = patch * merge
    bounds = {k: v for k, v in (("min_pixels", min_pixels), ("max_pixels", max_pixels)) if v is not None}
    h, w = smart_resize(size[0], size[1], factor=factor, **bounds)
    return h // factor, w // factor


def image_token_counts(grid_thw: torch.Tensor, merge: int) -> list[int]:
    """Tokens Qwen's merger makes of each image of a processor call: its patch grid over merge x merge blocks."""
    return (grid_thw.prod(-1) // merge ** 2).tolist()


def raster_patches(hidden: torch.Tensor, images: int, gh: int, gw: int, merge: int) -> torch.Tensor:
    """Qwen's ViT states, in merge-block order ((gh/m, gw/m, m, m) per image), as a raster patch grid
    [images, gh, gw, C]."""
    blocks = hidden.reshape(images, gh // merge, gw // merge, merge, merge, -1)
    return blocks.permute(0, 1, 3, 2, 4, 5).reshape(images, gh, gw, -1)


def vit_outputs(visual: nn.Module, pixel_values: torch.Tensor,
                grid_thw: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Qwen2.5-VL's ViT on one processor call's images of one size: (pre-merger patch grid [N, gh, gw, C] in raster
    order, post-merger tokens [N, gh/2 * gw/2, D] in the order Qwen scatters them into the prompt), both fp32."""
    device = next(visual.parameters()).device
    thw = grid_thw.to(device)
    out = visual(pixel_values.to(device, visual.dtype), grid_thw=thw)
    m = visual.spatial_merge_size
    _, gh, gw = thw[0].tolist()
    size = len(thw)
    # ViT states come in window order, by merge block: back to the processor's block order, then raster
    window, _ = visual.get_window_index(thw)
    hidden = out.last_hidden_state.view(-1, m * m, out.last_hidden_state.shape[-1])[torch.argsort(window)]
    grid = raster_patches(hidden, size, gh, gw, m)
    tokens = out.pooler_output.view(size, (gh // m) * (gw // m), -1)
    return grid.float(), tokens.float()



def projected_rows(tower: nn.Module, connector: nn.Module, features: torch.Tensor, images: int,
                   cameras: int) -> torch.Tensor:
    """The cached features of `images` images, [images x tokens, C] (what a grafted Qwen reads as
    `pixel_values`), through the pass-through and the projector: [images x tokens, D]. The projector sees them a
    sample a row, [images / cameras, cameras x tokens, C]: a fused projector (graftcache.graft.FusedProjector)
    routes rows."""
    hidden = tower(features).last_hidden_state
    return connector(hidden.reshape(images // cameras, -1, hidden.shape[-1])).flatten(0, 1)


def projected_images(tower: nn.Module, connector: nn.Module, features: torch.Tensor, grid_thw: torch.Tensor,
                     merge: int, cameras: int) -> tuple[torch.Tensor, ...]:
    """What a grafted `get_image_features` returns as its `pooler_output`: the cached features of every image
    (one per camera, sample after sample) projected a sample a row (`projected_rows`), split per image as Qwen
    splits its own tokens."""
    tokens = projected_rows(tower, connector, features, len(grid_thw), cameras)
    return torch.split(tokens, image_token_counts(grid_thw, merge))


def qwen3_vl_image_features(tower: nn.Module, connector: nn.Module, qwen: nn.Module, features: torch.Tensor,
                            grid_thw: torch.Tensor, cameras: int, deepstack: list | None):
    """What a grafted Qwen3-VL `get_image_features` returns (GR00T, VLA-JEPA): the cached features [images x tokens,
    C] through the pass-through and the projector, split per image as Qwen splits them (`projected_images`), and
    `deepstack` for the deepstack features: the policy's own "none" (a grafted encoder has no inner ViT blocks for
    the deepstack mergers to read). The projector sees them a sample a row, [B, cameras x tokens, C], so a fused
    projector (graftcache.graft.FusedProjector) routes rows."""
    from transformers.models.qwen3_vl.modeling_qwen3_vl import BaseModelOutputWithDeepstackFeatures

    tokens = projected_images(tower, connector, features, grid_thw, qwen.visual.spatial_merge_size, cameras)
    return BaseModelOutputWithDeepstackFeatures(last_hidden_state=features, pooler_output=tokens,
                                                deepstack_features=deepstack)


def cached_token_count(name: str, batch: Mapping[str, Any], camera_keys: Sequence[str]) -> int:
    """The cached tokens per camera of a grafted batch, refused in one line when a camera's features, the state
    or the task is missing or the cameras disagree."""
    missing = [k for k in [feature_key(c) for c in camera_keys] + [STATE, "task"] if k not in batch]
    if missing:
        raise BackboneError(f"{name} batch is missing {', '.join(missing)}")
    counts = {k: batch[feature_key(k)].shape[1] for k in camera_keys}
    if len(set(counts.values())) != 1:
        raise BackboneError(f"{name}: cameras carry different token counts ({counts})")
    return next(iter(counts.values()))


def check_slots(name: str, tokens: set[int], slots: set[int]) -> None:
    """Refuse cached features whose tokens per camera are not the prompt's one size of image slots."""
    if tokens != slots or len(slots) != 1:
        raise BackboneError(f"{name}: cached features have {sorted(tokens)} tokens per camera; the prompt "
                            f"has {sorted(slots)} image slots per camera")


def prompt_grid(name: str, policy: str, token_grid: tuple[int, int], tokens: int) -> tuple[int, int]:
    """The merged grid a prompt needs for `tokens` cached tokens per camera: the token grid, or the square grid
    of a pooling control (the cache keeps no shape, so any other count is refused, not guessed)."""
    gh, gw = token_grid
    if tokens == gh * gw:
        return gh, gw
    side = round(tokens ** 0.5)
    if side * side != tokens:
        raise BackboneError(f"{name}: {tokens} cached tokens per camera is neither the token grid {gh}x{gw} nor "
                            f"a square one; {policy}'s prompt needs the grid's shape")
    return side, side
