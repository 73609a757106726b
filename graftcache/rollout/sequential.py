"""Episodes where they decide something: `rollout --until-resolved CAP` adds paired episodes to the candidate
encoders whose closed-loop order is still unresolved, a look at a time, instead of the same count for every cell.

The question a user brings is pairwise: of two candidate encoders, which one makes the policy act better?
graftcache.analysis.pairwise answers it per pair of encoders of a (backbone, suite), from episodes paired by fit seed
and episode key. Most pairs are settled by a few episodes, a few need many: spending the same count on every cell
wastes the simulator on the settled ones and starves the close ones (Beyond Binary Success, arXiv 2603.13616: graded
progress with sequential tests).

The design, a group-sequential test with a fixed number of looks:
- look j (1, 2, ...) has every selected cell's first j * STEP episodes per task, STEP being the request's
  `episodes_per_task`; the first look is the request as it would run without this mode (every selected cell);
- after each look, the plain-graft (candidate) pairs of each (backbone, suite) whose closed-loop interval still holds
  0 are unresolved; only the cells of their two encoders get the next look's episodes (a cell of an encoder in no
  unresolved pair gets none);
- it stops when no pair is unresolved or when the next look would pass CAP episodes per task (looks = ceil(CAP /
  STEP); the last may add fewer than STEP);
- every look's interval is taken at level 1 - error / looks (Bonferroni over the looks): whatever look a pair stops
  at, the chance that it is called resolved when its two encoders are in truth equal in closed loop is at most
  `error` (5%) per pair. Bonferroni is conservative against a Pocock or O'Brien-Fleming boundary, but needs no
  assumption about how the looks' statistics correlate, which paired graded measures over a few seeds do not give;
- a look is decided from its own episodes only (the first j * STEP of each cell, by episode index), so a rerun after a
  kill replays the same decisions from the rows on file and runs only what is missing: resumable like every
  rollout.

What the looks decided goes beside the rollouts file (graftcache.analysis.looks: typed, versioned JSON), which the
report reads to state the error rate and to take the closed-loop intervals at the level the looks used.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass

import polars as pl

from graftcache.analysis import PLAIN
from graftcache.analysis.looks import Look, Looks, looks_file
from graftcache.analysis.pairwise import NOT_RESOLVED, pairwise
from graftcache.analysis.rollouts import HIGHER_IS_BETTER, read_rollouts
from graftcache.errors import RolloutError
from graftcache.rollout.episodes import Simulator, episodes_of
from graftcache.rollout.request import MAX_EPISODES_PER_TASK, RolloutRequest
from graftcache.rollout.select import Selection


@dataclass(frozen=True)
class Sequential:
    """What `--until-resolved` asks: at most `cap` episodes per task a cell, `error` the chance per pair, over every
    look, of calling a pair of equal encoders resolved, judged on `measure` (a graded measure or success)."""

    cap: int
    error: float = 0.05
    measure: str = "min_target_distance_m"

    def __post_init__(self) -> None:
        if not 1 <= self.cap <= MAX_EPISODES_PER_TASK:
            raise RolloutError(f"--until-resolved {self.cap}: must be 1 to {MAX_EPISODES_PER_TASK} episodes per task")
        if not 0 < self.error < 1:
            raise RolloutError(f"sequential error rate {self.error}: must lie strictly between 0 and 1")
        if self.measure not in HIGHER_IS_BETTER:
            raise RolloutError(f"sequential measure {self.measure}: not a closed-loop measure; choose from "
                               f"{', '.join(HIGHER_IS_BETTER)}")

    def looks(self, step: int) -> int:
        """How many looks at most, each adding `step` episodes per task (the last up to the cap)."""
        return math.ceil(self.cap / step)

    def level(self, step: int) -> float:
        """Each look's interval level: the error spent evenly over the looks."""
        return 1 - self.error / self.looks(step)


def unresolved(candidates: pl.DataFrame, rollouts: pl.DataFrame, seq: Sequential, level: float) -> pl.DataFrame:
    """The candidate pairs whose closed-loop interval at `level` holds 0, or who have none yet (fewer than 2 paired
    episodes): graftcache.analysis.pairwise's rows."""
    verdicts = pairwise(candidates, rollouts, measure=seq.measure, closed_level=level)
    return verdicts.filter(pl.col("closed").is_null() | (pl.col("closed") == NOT_RESOLVED))


def looks(sel: Selection, sim: Simulator, *, seq: Sequential,
          log: Callable[[str], None]) -> Iterator[Selection]:
    """The selections of each look, in turn: a caller rolls each out before asking for the next, which is decided
    from the rows that one wrote (see the module docstring). Writes the looks' record (graftcache.analysis.looks)
    once the last look is decided. Without two candidate encoders on any (backbone, suite) there is no pair to
    judge: the request runs as it is, in one look."""
    req = sel.req
    step = req.episodes_per_task
    if step > seq.cap:
        raise RolloutError(f"--episodes-per-task {step} is past --until-resolved {seq.cap}: the first look would "
                           "already pass the cap")
    candidates = sel.rows.filter(pl.col("control") == PLAIN)
    n_looks, level = seq.looks(step), seq.level(step)
    log(f"sequential rollout: up to {n_looks} look(s) of {step} episode(s) per task (cap {seq.cap}); each pair's "
        f"closed-loop {seq.measure} interval at {level:.2%}, so a pair of equal encoders is called resolved with "
        f"chance <= {seq.error:.0%} over all looks (Bonferroni)")
    history: list[Look] = []
    current = sel
    pairs = candidates.group_by("backbone", "suite").agg(pl.col("encoder").n_unique() > 1)["encoder"].any()
    for look in range(1, n_looks + 1):
        yield current
        asked = current.req
        if not pairs:
            log("sequential rollout: no (backbone, suite) has two candidate encoders, no pair to judge: one look")
            history.append(Look(look, asked.episodes_per_task, current.rows.height, ()))
            break
        # judged on every candidate's first episodes_per_task episodes, whichever cells this look ran
        judged = {e.id for e in episodes_of(candidates, asked, sim)}
        rollouts = read_rollouts(req.rollouts, sel.results, where=pl.col("episode_id").is_in(judged))
        open_pairs = unresolved(candidates, rollouts, seq, level).select("backbone", "suite", "encoder_a",
                                                                         "encoder_b")
        history.append(Look(look, asked.episodes_per_task, current.rows.height, tuple(open_pairs.rows())))
        if not open_pairs.height or look == n_looks:
            break
        current = sel.narrowed(_cells_of(candidates, open_pairs), episodes_per_task=min(seq.cap, (look + 1) * step))
        log(f"look {look}: {open_pairs.height} pair(s) unresolved ("
            + "; ".join(f"{a} vs {b} on {backbone}/{suite}" for backbone, suite, a, b in open_pairs.rows())
            + f"): {current.rows.height} cell(s) to {current.req.episodes_per_task} episodes per task")
    _write_record(req, seq, step, history)


def _cells_of(candidates: pl.DataFrame, pairs: pl.DataFrame) -> pl.DataFrame:
    """The candidate cells (rows) of every encoder named by `pairs` on its (backbone, suite)."""
    named = pl.concat([pairs.select("backbone", "suite", pl.col(side).alias("encoder"))
                       for side in ("encoder_a", "encoder_b")]).unique()
    return candidates.join(named, on=["backbone", "suite", "encoder"], how="semi")


def _write_record(req: RolloutRequest, seq: Sequential, step: int, history: Sequence[Look]) -> None:
    """The looks' record beside the rollouts file, written whole (a temporary name, then renamed over it)."""
    record = Looks(seq.measure, seq.error, seq.cap, step, seq.looks(step), seq.level(step), tuple(history),
                   req.command)
    path = looks_file(req.rollouts)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text(json.dumps(record.as_json(), indent=1) + "\n")
    os.replace(tmp, path)
