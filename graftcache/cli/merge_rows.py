"""`graftcache merge-rows`: append rows kept aside (a cell's row.parquet when its results file could not be
written, or another results file) to a results file, under its writers' lease like any append."""

from __future__ import annotations

import argparse


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("merge-rows", help="append kept rows (a run folder's row.parquet) to a results file",
                       description="Append the rows of results files (the row.parquet a fit keeps in a cell's run "
                       "folder when its results file cannot be written, or any other results file) to --results. "
                       "A row whose run_id the file already has replaces it, so merging twice changes nothing.")
    p.add_argument("rows", nargs="+", help="row.parquet files (or results files) to merge")
    p.add_argument("--results", required=True, help="results Parquet file to merge them into")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from graftcache.results import done_run_ids
    from graftcache.results.claims import merge

    had = done_run_ids(args.results)
    rows = merge(args.results, args.rows)
    new = rows.filter(~rows["run_id"].is_in(list(had))).height
    print(f"merged {len(rows)} row(s) into {args.results}: {new} new, {len(rows) - new} replacing rows of the same "
          "run_id")
    return 0
