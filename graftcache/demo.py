"""The offline demo: cli/demo.toml on the bundled LIBERO sample, then the report.

The recipe lives in the checkout's cli/ folder beside the package (an editable install, as the
README sets up); `--recipe` runs another. A relative results path is placed under the cache root
(`$GRAFTCACHE_HOME/demo/...`), beside the caches and tiny backbones it comes from, so a rerun from
any folder reuses every cell and the analysis notebook finds the table by default. The report cites
the exact commands and cache keys behind its numbers, and warns on every row that ran on random-init
weights.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import graftcache
from graftcache.errors import GraftcacheError
from graftcache.progress import write
from graftcache.recipe import load_recipe
from graftcache.report import ReportPaths, write_report
from graftcache.store import cache_root
from graftcache.sweep import run_sweep

DEFAULT_RECIPE = Path(graftcache.__file__).resolve().parents[1] / "cli" / "demo.toml"


def run_demo(recipe_path: str | Path | None = None, out: str | Path | None = None) -> ReportPaths:
    """Run the demo recipe (resumable) and write its report; returns the report's paths."""
    path = Path(recipe_path) if recipe_path else DEFAULT_RECIPE
    if not path.is_file():
        raise GraftcacheError(f"{path}: demo recipe not found (run from a checkout of graftcache, or pass --recipe)")
    t0 = time.perf_counter()
    recipe = load_recipe(path)
    if not Path(recipe.results).is_absolute():
        recipe = dataclasses.replace(recipe, results=str(cache_root(recipe.cache) / recipe.results))
    state = run_sweep(recipe)
    report_dir = Path(out) if out else Path(recipe.results).parent / "report"
    commands = {"demo": f"graftcache demo --recipe {path}", "sweep": f"graftcache sweep {path}", **state.commands}
    paths = write_report(recipe.results, report_dir, commands=commands)
    write(f"demo finished in {time.perf_counter() - t0:.0f}s")
    return paths
