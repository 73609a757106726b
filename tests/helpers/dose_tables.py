"""The dose curves' hand table (tests/analysis/test_dose_curves.py, tests/report/test_report_dose.py), its answers
worked out by hand.

smolvla/libero_object, encoder siglip at doses 0 (plain), 0.25, 0.5, 0.75 (noise-A) and 1 (zero-image), seeds 0-2,
4 episodes a seed on shared keys. Offline (OFFLINE) each step rises except the last (0.75 -> 1 falls by 0.06, within
noise). In the closed loop (LOOP: a dose's mean distance; every episode k shifts all doses alike by EPISODE[k], and
JITTER is small): 0 -> 0.25 and 0.5 -> 0.75 rise clearly, 0.25 -> 0.5 rises by 1 cm (offline +0.02) and is confirmed,
0.75 -> 1 rises clearly while offline falls. So the resolution is the 0.25 -> 0.5 step's offline gap, 0.02.
dinov2-s has noise-0.5 cells but no zero-image cells of its own: siglip's stand in at dose 1, and its closed loop
was never rolled out (no resolution, a note).
"""

from __future__ import annotations

import numpy as np
import polars as pl

from helpers.tables import row, table

CONTROLS = {0.0: "none", 0.25: "noise-0.25", 0.5: "noise-0.5", 0.75: "noise-0.75", 1.0: "zero-image"}
OFFLINE = {0.0: [1.00, 1.02, 0.98], 0.25: [1.11, 1.12, 1.08], 0.5: [1.13, 1.15, 1.09], 0.75: [1.40, 1.38, 1.45],
           1.0: [1.35, 1.36, 1.34]}
LOOP = {0.0: 0.05, 0.25: 0.10, 0.5: 0.11, 0.75: 0.30, 1.0: 0.50}
EPISODE = (0.0, 0.04, -0.03, 0.08)
JITTER = np.random.default_rng(0).uniform(-0.002, 0.002, size=(5, 3, 4))


def dose_tables() -> tuple[pl.DataFrame, pl.DataFrame]:
    """(results, rollouts episodes) as described above."""
    rows, episodes = [], []
    for d, (dose, control) in enumerate(CONTROLS.items()):
        for seed, mse in enumerate(OFFLINE[dose]):
            r = row("smolvla", "libero_object", "siglip", seed, mse, control=control)
            rows.append(r)
            for k, shift in enumerate(EPISODE):
                episodes.append({"run_id": r["run_id"], "success": False, "suite": "libero_object", "task_index": 0,
                                 "episode": k, "seed": 100 + k, "max_steps": 40, "perturbation_m": 0.03,
                                 "min_target_distance_m": LOOP[dose] + shift + JITTER[d, seed, k]})
    rows += [row("smolvla", "libero_object", "dinov2-s", s, m, control=c)
             for s in range(3) for c, m in (("none", 1.2 + s / 100), ("noise-0.5", 1.3 + s / 100))]
    return table(rows), pl.DataFrame(episodes)
