"""`graftcache sweep RECIPE`: the cells of a TOML recipe (cli/paper.toml, cli/demo.toml)."""

from __future__ import annotations

import argparse
import dataclasses

from graftcache.cli.common import add_flag, add_flags, given
from graftcache.requests import ExecutorSettings, FitRequest


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("sweep", help="run the extracts and fits of a TOML recipe (resumable)",
                       description="Extract every missing cache, then fit every missing cell a recipe "
                       "describes (encoders x suites x backbones x seeds + controls). Rows already in the results "
                       "file are skipped, so an interrupted sweep continues where it stopped.")
    p.add_argument("recipe", help="TOML recipe, e.g. cli/paper.toml")
    p.add_argument("--dry-run", action="store_true",
                   help="run every check the sweep runs before its first step (recipe, dataset, suites' "
                   "splits, encoders, memory) and print what it found; train, extract and fit nothing")
    add_flags(p, ExecutorSettings, overrides=True)  # over the recipe's [executor] section (else the defaults shown)
    add_flag(p, FitRequest, "cells_per_pass", overrides=True)  # over the recipe's [fit] section
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from graftcache.recipe import load_recipe
    from graftcache.sweep import check_sweep, run_sweep

    recipe = load_recipe(args.recipe)
    if "cells_per_pass" in vars(args):  # --cells-per-pass, over the recipe's [fit] section
        recipe = dataclasses.replace(recipe, fit={**recipe.fit, "cells_per_pass": args.cells_per_pass})
    settings = dataclasses.replace(recipe.executor_settings, **given(ExecutorSettings, args))
    if args.dry_run:
        notes = check_sweep(recipe)  # every check the run makes before its first step
        print(f"{recipe.path}: {recipe.n_fits} cells, {recipe.n_rows} distinct rows -> {recipe.results}")
        print(f"  dataset   {recipe.dataset}")
        print(f"  backbones {', '.join(f'{b.name} ({b.policy})' for b in recipe.backbones)}")
        print(f"  encoders  {', '.join(e.label for e in recipe.encoders)}")
        print(f"  suites    {', '.join(recipe.suites)}; seeds {', '.join(map(str, recipe.seeds))}")
        print(f"  controls  {', '.join(recipe.controls) or '(none)'}; objective {recipe.objective}")
        print(f"  executor  {settings.executor}" + (f" at {settings.address}" if settings.address else ""))
        for line in notes:
            print(f"  {line}")
        return 0
    run_sweep(recipe, settings=settings)
    print(recipe.results)
    return 0
