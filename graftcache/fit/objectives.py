"""Objectives: how a cell's grafted projector is fitted, declared as data (a registry, no if-chains).

- flow   the policy's own flow-matching loss, back-propagated into the projector (and LoRA), for `steps`
         AdamW steps of `batch_size` at `lr` (fit/loop.py); the cells of a backbone pass step together
         (graftcache/fit/passes.py), one cell being the case of one
- align  closed-form ridge regression of the native tower's post-connector tokens on the candidate's
         features (fit/align.py): no steps, no learning rate, needs the native tower's cache
- align-flow  align's closed form as the projector's starting point, then flow's steps from there: a short fit
         (the demo's) starts where the projector already speaks the backbone's token language, so its steps go
         into what the flow loss adds instead of into learning that language from a random projector
- eval   (not selectable) controls that train nothing, such as `native`, are scored as loaded
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from contextlib import ExitStack, closing, contextmanager
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import torch

from graftcache.errors import FitError
from graftcache.fit.align import fit_ridge
from graftcache.fit.buffer import ShuffleBuffer, buffer_frames
from graftcache.fit.controls import Control, get_control
from graftcache.fit.dose import FrameTransform
from graftcache.fit.feed import SplitFeed
from graftcache.fit.loop import Route, alone, learner, optimise_together
from graftcache.fit.stream import FeatureSource, StreamStats, read_blocks
from graftcache.requests import FitRequest

if TYPE_CHECKING:
    from graftcache.backbones.base import BackboneAdapter


@dataclass(frozen=True)
class Fitting:
    """What an objective fits one cell from: the grafted adapter, the cell's trainable parameters and its train
    split as it streams."""

    adapter: BackboneAdapter
    req: FitRequest
    control: Control
    seen: FrameTransform                        # what the cell's policy sees of a batch (its control, its dose)
    params: Sequence[torch.nn.Parameter]        # what this cell trains (its projector; LoRA's too when alone)
    train: SplitFeed                            # the train split, paired by the control
    cams: Mapping[str, str]                     # policy camera -> cache camera
    targets: tuple[FeatureSource, np.ndarray] | None  # native post-connector tokens, their cache row per train frame
    grid: tuple[int, int]
    seed: int
    dtype: torch.dtype
    stats: StreamStats                          # what the streams dropped and copied


@contextmanager
def flow_buffer(train: SplitFeed, req: FitRequest, seed: int, stats: StreamStats) -> Iterator[ShuffleBuffer]:
    """The shuffle buffer a flow fit draws its batches from (`req.buffer_mib`), over the train split's endless
    stream in the order `seed` gives; the stream's readers stop when the block ends."""
    capacity = buffer_frames(req.buffer_mib, train.source.frame_bytes(), req.batch_size, len(train.low))
    with closing(read_blocks(train.features(seed=seed), req.num_workers, stats)) as blocks:
        yield ShuffleBuffer(blocks, capacity, empty_limit=train.n_blocks)


def _flow(cells: Sequence[Fitting], route: Route) -> list[float]:
    """The flow steps of every cell of a pass (one cell: a pass of one), in one forward and backward of the policy
    per step; each cell's final loss (NaN for a cell with nothing to train)."""
    first = cells[0]
    if not all(f.params for f in cells):
        return [float("nan")] * len(cells)
    with ExitStack() as stack:
        learners = [learner(f.train.low, stack.enter_context(flow_buffer(f.train, f.req, f.seed, f.stats)), f.cams,
                            f.params, batch_size=f.req.batch_size, lr=f.req.lr, seed=f.seed,
                            transform=f.seen) for f in cells]
        optimise_together(first.adapter, learners, steps=first.req.steps, batch_size=first.req.batch_size,
                          dtype=first.dtype, route=route, show=first.req.progress, leave=False)
    return [one.final_loss for one in learners]


def _align(f: Fitting) -> float:
    cameras = list(f.cams.values())

    def pairs(blocks: Iterator) -> Iterator[tuple[torch.Tensor, torch.Tensor]]:
        for block in blocks:
            seen, native = f.seen(block.features[0], f.train.low.rows[block.owners]), block.features[1]
            yield from ((seen[c], native[c]) for c in cameras)

    with closing(read_blocks(f.train.with_targets(*f.targets), f.req.num_workers, f.stats)) as blocks:
        return 1.0 - fit_ridge(f.adapter.projector, pairs(blocks), f.grid)


def _align_flow(f: Fitting) -> float:
    _align(f)
    return _flow([f], alone)[0]


def _nothing(f: Fitting) -> float:
    return float("nan")


def alone_only(fit: Callable[[Fitting], float]) -> Callable[[Sequence[Fitting], Route], list[float]]:
    """An objective whose cells never share a pass (`fuses` False), as a pass of one."""

    def one(cells: Sequence[Fitting], route: Route) -> list[float]:
        if len(cells) != 1:
            raise FitError(f"{len(cells)} cells in one pass of an objective whose cells run alone")
        return [fit(cells[0])]

    return one


@dataclass(frozen=True)
class Objective:
    name: str
    fit: Callable[[Sequence[Fitting], Route], list[float]]  # fits the grafted projectors of a pass's cells (`route`:
                                      # whose rows are whose); returns each cell's final training loss
    scheduled: bool = False           # steps / lr / batch_size / buffer_mib are part of its cells (else 0)
    needs_native: bool = False        # reads the native tower's cache (its regression targets)
    fuses: bool = False               # its cells may share backbone passes (graftcache/fit/passes.py): a gradient
                                      # step per batch; align's closed form and eval's nothing gain nothing from it


OBJECTIVES: dict[str, Objective] = {
    "flow": Objective("flow", _flow, scheduled=True, fuses=True),
    "align": Objective("align", alone_only(_align), needs_native=True),
    "align-flow": Objective("align-flow", alone_only(_align_flow), scheduled=True, needs_native=True),
}
EVAL_ONLY = Objective("eval", alone_only(_nothing))


def reads_native(objective: str, controls: Iterable[str]) -> bool:
    """Whether a fit of `objective` with `controls` reads the native tower's cache (its targets, or its features), so
    that a sweep extracts that cache first and its dry run lists it."""
    return OBJECTIVES[objective].needs_native or any(get_control(c).native_cache for c in controls)
