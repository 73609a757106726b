"""`graftcache rollout RESULTS`: the top cells of a results file (or exact run_ids) exported and run in the LIBERO
simulator, one rollouts row per episode (graftcache.rollout)."""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable
from functools import partial
from pathlib import Path

from graftcache.analysis.looks import LOOKS_FILE
from graftcache.checks import IntList
from graftcache.cli.common import add_flags, request_from
from graftcache.cli.report import SCORE_NAMES
from graftcache.codecs import int_list
from graftcache.requests import DEVICE_HELP, ExecutorSettings
from graftcache.rollout.request import EXPORTS_FOLDER, RESETS, ROLLOUTS_FILE

#: LIBERO suites hold 10 tasks (libero_90: 90)
TASKS = IntList("task", 89, 90)


def _at_least(low: int) -> Callable[[str], int]:
    """A flag's parser of integers >= `low` (argparse's one-line usage error otherwise)."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
        if value < low:
            raise argparse.ArgumentTypeError(f"{text!r}: must be {low} or more")
        return value

    return parse


def _centimetres(text: str) -> float:
    """--perturb-cm's parser: a finite number >= 0 (its upper bound is RolloutRequest's)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not math.isfinite(value) or value < 0:
        raise argparse.ArgumentTypeError(f"{text!r}: must be a finite number of centimetres, 0 or more")
    return value


def _names(text: str) -> tuple[str, ...]:
    names = tuple(dict.fromkeys(n.strip() for n in text.split(",") if n.strip()))
    if not names:
        raise argparse.ArgumentTypeError(f"{text!r} names nothing")
    return names


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("rollout", help="run the best cells of a results file in the LIBERO simulator (closed loop)",
                       description="Export the K best encoders of every (backbone, suite) of RESULTS, ranked by "
                       "the report's score (every seed's row), with their zero-image rows and the backbone's native "
                       "rows, or exactly --run-ids, and run each in LIBERO through lerobot's own evaluation loop "
                       "(the suite's official init states, every cell on the same seeds). One row per episode goes "
                       "to the rollouts file; a rerun runs only the episodes it lacks. Needs the simulator: "
                       "`make setup-libero`.")
    p.add_argument("results", help="results Parquet file (written by fit/sweep/demo)")
    p.add_argument("--run-ids", type=_names, default=None, metavar="ID,...",
                   help="roll out exactly these rows (any control but shuffled-image) instead of the top cells")
    p.add_argument("--top", type=_at_least(1), default=3, metavar="K",
                   help="encoders per (backbone, suite), best first by --score (default: 3)")
    p.add_argument("--score", choices=SCORE_NAMES, default="mse", help="the report's ranking score (default: mse)")
    p.add_argument("--suites", type=_names, default=None, metavar="SUITE,...",
                   help="only cells fit on these suites (each cell runs in the suite it was fit on)")
    p.add_argument("--tasks", type=partial(int_list, rule=TASKS), default=None, metavar="0,1,...",
                   help="tasks of each suite (default: all of them)")
    p.add_argument("--episodes-per-task", type=_at_least(1), default=1, metavar="N",
                   help="episodes per task, episode k from the task's init state k (default: 1)")
    p.add_argument("--max-steps", type=_at_least(1), default=None, metavar="M",
                   help="step limit of an episode (default: lerobot's for the suite: 280 spatial/object, 300 goal, "
                   "520 libero_10)")
    p.add_argument("--seed", type=_at_least(0), default=1000,
                   help="episode k of every task and cell is seeded SEED + k, so cells are compared on the same "
                   "episodes (default: 1000, lerobot-eval's default --seed)")
    p.add_argument("--perturb-cm", type=_centimetres, default=0.0, metavar="X",
                   help="slide each episode's target object by a planar offset uniform in [-X, X] cm per axis after "
                   "the reset to its init state, redrawn when it does not settle where it was put (after 8 draws: "
                   "none), drawn from the episode's seed and task so every cell gets the same scenes, as the bundled "
                   "sample's demonstrations were rendered (X = 3); recorded in each row (default: 0, lerobot-eval's "
                   "official init states)")
    p.add_argument("--reset", choices=RESETS, default=RESETS[0],
                   help="how each episode's scene is reset to its init state: soft keeps the simulator and renders "
                   "only the images the policy sees, hard is lerobot-eval's own reset (a new simulator each "
                   "episode); both give the same episodes, state for state, so rows do not record it (default: "
                   f"{RESETS[0]})")
    p.add_argument("--device", default="cpu", metavar="DEVICE",
                   help=f"where each episode's policy runs: {DEVICE_HELP} (default: cpu). Its actions are computed "
                   "on that device's kernels, which each row records (column kernels): rows of one episode from "
                   "other kernels may differ. With --executor ray and cuda, each actor holds --gpus-per-task GPUs "
                   "(default 1; a fraction shares one)")
    p.add_argument("--until-resolved", type=_at_least(1), default=None, metavar="CAP",
                   help="sequential: after the first --episodes-per-task episodes, keep adding as many to the "
                   "candidate encoders (plain grafts) whose pairwise closed-loop order (closest approach, paired by "
                   "fit seed and episode) is still unresolved, up to CAP episodes per task a cell; each look's "
                   "interval is taken so that a pair of equal encoders is called resolved with chance <= 5%% over "
                   f"all looks (Bonferroni), recorded in {LOOKS_FILE} beside the rollouts file for the report "
                   "(default: off)")
    p.add_argument("--rollouts", default=None, metavar="PATH",
                   help=f"rollouts Parquet file to append to (default: {ROLLOUTS_FILE} beside RESULTS); exports go "
                   f"to {EXPORTS_FOLDER}/RUN_ID beside it")
    p.add_argument("--videos", action="store_true",
                   help="also write each episode's frames as an mp4, as lerobot-eval writes its videos, to "
                   "videos/RUN_ID/ beside the rollouts file; its row's video column holds the path relative to the "
                   "file (default: no videos; episodes already in the file are not rerun for one)")
    p.add_argument("--workers", type=_at_least(1), default=None, metavar="N",
                   help="episodes run at once, each in a worker process with a simulator of its own (default: 1, "
                   "in this process); the rows are those of one worker. At most one per CPU (more are capped, said in "
                   "one line): each policy runs on one torch thread. With --executor ray: Ray actors, each holding a "
                   "simulator (default: as many as the "
                   "cluster runs at once)")
    p.add_argument("--cache", default=None, help="cache root the fits read (default: $GRAFTCACHE_HOME or "
                   "~/.cache/graftcache)")
    p.add_argument("--runs", default=None, help="folder of run folders, when the fits wrote them elsewhere (--out)")
    add_flags(p, ExecutorSettings, skip=("shards",),
              cpus_per_task="CPUs per Ray actor (one simulator each)", gpus_per_task="GPUs per Ray actor (default 0)",
              max_retries="restarts of a Ray actor whose process or node died, its episode run again (an episode "
              "that raised an error is not)")
    p.set_defaults(func=run)


def _absolute(path: str | None) -> str | None:
    """A local path made absolute (the simulator may be built in another process or on another node), a URL or None
    as given."""
    from graftcache.store.roots import is_url

    return path if path is None or is_url(path) else str(Path(path).absolute())


def run(args: argparse.Namespace) -> int:
    from graftcache.executors import get_executor
    from graftcache.rollout import rollouts_file
    from graftcache.rollout.libero import LiberoSimulator
    from graftcache.rollout.request import RolloutRequest, default_rollouts
    from graftcache.rollout.roll_out import roll_out_started
    from graftcache.rollout.select import check_tasks, select
    from graftcache.runtime import resolve_device

    rollouts = Path(args.rollouts).absolute() if args.rollouts else default_rollouts(args.results)
    req = RolloutRequest(results=Path(args.results).absolute(), rollouts=rollouts, run_ids=args.run_ids,
                         top=args.top, suites=args.suites, score=args.score, tasks=args.tasks,
                         episodes_per_task=args.episodes_per_task, max_steps=args.max_steps, seed=args.seed,
                         perturb_cm=args.perturb_cm, reset=args.reset, device=args.device,
                         command=args.command_line)
    # both files, the rows and their tasks checked before the simulator's imports (the team starts them); the rows
    # are chosen once (and said once), and handed on
    sel = select(req)
    check_tasks(sel.rows, req.tasks)
    rollouts_file.read(req.rollouts)
    resolve_device(req.device)  # a device this machine lacks, refused before any simulator starts
    spawn = partial(LiberoSimulator, req.results, rollouts.parent / EXPORTS_FOLDER, cache=_absolute(args.cache),
                    runs=_absolute(args.runs), max_steps=args.max_steps, videos=args.videos, device=req.device)
    expand = None
    if args.until_resolved is not None:
        from graftcache.rollout.sequential import Sequential, looks

        expand = partial(looks, seq=Sequential(args.until_resolved), log=print)
    executor = get_executor(request_from(ExecutorSettings, args))
    # the team starts first: its simulators build while this process builds its own, which says what its suites are
    roll_out_started([sel], spawn, executor.rollout_team(sel.req, spawn, args.workers, print), expand=expand)
    return 0
