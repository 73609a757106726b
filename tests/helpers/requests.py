"""The one builder of test requests: the settings every test extraction and fit shares (random-init encoder
weights, no worker processes, no progress bar, one seed, a tiny split), plus what a module or a test varies.

A module fixes its own settings once with functools.partial (`_req = partial(extract_request, encoder=...,
grids=...)`); a test passes what it varies as keywords, which win over both.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from graftcache.requests import ExtractRequest, FitRequest

#: What every test extraction shares: cheap, in-process, quiet.
EXTRACT = {"random_init": True, "num_workers": 0, "progress": False}
#: What every test fit shares: one seed of libero_spatial, half the episodes held out, a 4-frame batch.
FIT = {"suite": "libero_spatial", "seeds": (0,), "batch_size": 4, "eval_fraction": 0.5, "progress": False,
       "command": "pytest"}


def extract_request(dataset: str | Path, cache: str | Path, **settings: Any) -> ExtractRequest:
    """An ExtractRequest of `dataset` into the cache root `cache`: EXTRACT, then `settings`."""
    return ExtractRequest(**{**EXTRACT, "dataset": str(dataset), "cache": str(cache), **settings})


def fit_request(backbone: str, policy: str | Path, dataset: str | Path, cache: str | Path, under: Path,
                **settings: Any) -> FitRequest:
    """A FitRequest of `policy` (a `backbone` checkpoint) on caches of `dataset` in the root `cache`, writing
    `under`/results.parquet and `under`/runs: FIT, then `settings`."""
    return FitRequest(**{**FIT, "backbone": backbone, "policy": str(policy), "dataset": str(dataset),
                         "cache": str(cache), "results": str(under / "results.parquet"), "out": str(under / "runs"),
                         **settings})
