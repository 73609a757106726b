"""`graftcache report`: rankings, transfer verdicts and figures from a results file."""

from __future__ import annotations

import argparse

from graftcache.cli.common import LazyText

#: `graftcache.analysis.scores.SCORES`'s names as plain data (building the parser imports no analysis;
#: tests/test_settings.py keeps the two equal)
SCORE_NAMES = ("mse", "ci-mse")


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("report", help="write report.md/report.html with figures from a results file",
                       description=LazyText(_description))
    p.add_argument("results", help="results Parquet file (written by fit/sweep/demo, or any table with the "
                   "columns above)")
    p.add_argument("--out", default="report", help="output folder (default: report/); transfer.csv, one row per "
                   "transfer verdict, is written there too")
    p.add_argument("--score", choices=SCORE_NAMES, default="mse",
                   help="rank encoders by offline action MSE (mse, the default) or critical-interval MSE (ci-mse: "
                   "the error near gripper open/close transitions); where the table holds both, the report "
                   "shows where the two rankings disagree")
    p.add_argument("--rollouts", metavar="PATH",
                   help="rollouts Parquet file (one row per episode; only its run_id and success columns are read, "
                   "so episodes run with other tools join too): adds each rolled-out cell's success rate (95%% Wilson "
                   "interval) and, per backbone and suite, Spearman, Kendall tau-b and MMRV of every offline score "
                   "(eval_mse, eval_ci_mse, eval_mse_arm, eval_mse_gripper) against success, in the report and in "
                   "closed_loop.csv; a run_id not in RESULTS is refused")
    p.set_defaults(func=run)


def _description() -> str:
    from graftcache.results import REPORT_COLUMNS  # imported to print help only: it loads the store

    return ("Turn a results Parquet file into rankings, near-tie bands, transfer verdicts in both directions, control "
            "comparisons and figures (report.md, report.html, PNGs). Any table with the columns "
            f"{', '.join(REPORT_COLUMNS)} can be reported (older versions, other tools, numbers typed in from a "
            "paper); without per-episode MSEs the bootstrap is seed-level, and the report says so.")


def run(args: argparse.Namespace) -> int:
    from graftcache.report import report_command

    return report_command(args.results, args.out, command=args.command_line, score=args.score,
                          rollouts=args.rollouts)
