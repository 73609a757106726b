"""What every report figure is drawn on: a bare Agg figure (no pyplot state, so reports stay headless and the
notebook shows the very same Figure objects), a panel grid, and value axes fitted to the data."""

from __future__ import annotations

from collections.abc import Sequence

from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

VALUE_MARGIN = 0.12  # share of the data's range added on each side of a value axis


def new_figure(width: float, height: float) -> Figure:
    fig = Figure(figsize=(width, height), layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def grid(n: int, max_cols: int = 4) -> tuple[int, int]:
    """(rows, columns) of a grid of n panels, at most max_cols wide."""
    cols = min(n, max_cols)
    return -(-n // cols), cols


def value_limits(values: Sequence[float]) -> tuple[float, float]:
    """Axis limits from the data plus VALUE_MARGIN, not from zero: encoders a few percent apart must look
    apart. Non-negative data (MSEs, distances) never get a negative lower limit."""
    lo, hi = min(values), max(values)
    pad = VALUE_MARGIN * ((hi - lo) or abs(hi) or 1.0)
    return max(lo - pad, min(lo, 0.0)), hi + pad
