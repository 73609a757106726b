"""The size of lerobot/libero per suite, as data with no imports: devtools.tile builds stand-ins of this size, and
benchmarks/bench_protocol.py (also run on a GPU machine without polars or PyAV) projects a protocol's cost on it."""

#: lerobot/libero per suite: (episodes, frames). Spatial, libero_10 and the totals (1,693 / 273,465) are
#: measured; object and goal frames are derived so that the suites add up to the total.
LIBERO_COUNTS: dict[str, tuple[int, int]] = {
    "libero_spatial": (432, 52_970),
    "libero_object": (454, 66_984),
    "libero_goal": (428, 52_042),
    "libero_10": (379, 101_469),
}
