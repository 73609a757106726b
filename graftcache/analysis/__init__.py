"""Questions asked of a results table, one function each: polars in, polars out.

A table needs only graftcache.results.REPORT_COLUMNS (backbone, suite, encoder, control, seed, eval_mse);
`analyze` fills every other SCHEMA column with nulls, so tables from older versions, other tools or a
paper are analysed like the ones `graftcache fit` writes.

The paper's question is whether the ranking of vision encoders found on a small frozen backbone (SmolVLA)
transfers to a large one (pi0.5), and back. Any number of backbones can be asked it: they stand on a ladder
ordered by parameter count (`backbone_params`, graftcache.analysis.ladder), every pair is judged in both
directions, and the headline (graftcache.analysis.headline) says whether the smallest backbone's winner
lands in the largest one's top tier and at which rung the ranking breaks. Seeds are few and offline MSE is
noisy, so "the winner" is compared against a *top tier*: every encoder whose MSE cannot be separated from the
best one's under a bootstrap. Encoders are ranked by one score, offline action MSE or CI-MSE
(graftcache.analysis.scores); the other is compared with it where the table holds both.

Statistics (stated once here, cited by the report):
- the unit of replication is the seed (projector init + data order); when rows carry per-episode MSEs in
  the list column `eval_mse_episodes`, the bootstrap is two-level (seeds, then held-out episodes within
  each drawn seed), otherwise it resamples seeds only (a seed-level bootstrap; `episode_coverage` says
  which cells had episodes);
- encoder e is in the top tier of a (backbone, suite) unless P(mean_e* > mean_best*) >= confidence over
  `n_boot` independent bootstrap replicates of both cells (a one-sided test at `confidence`; both, and the
  generator `seed`, are the fields of BootSettings, which holds their defaults);
- with a single seed and no episodes the bootstrap is degenerate, so the tier is the exact ties of the best
  mean; such rows are flagged in `basis`;
- every replicate draw comes from a generator seeded by (seed, control, backbone, suite, encoder), so
  results are deterministic and do not depend on row order;
- transfer is tested in both directions (smaller -> larger and larger -> smaller) for every pair of
  backbones, per suite and per seed-level cell (one seed's rows alone); a target tier that holds every
  shared encoder is a near-tie band, not a transfer (see graftcache.analysis.transfer);
- the controls' two findings hold "on every seed" when one side's worst seed is below the other's best (no
  bootstrap): the backbone's own tower against zero-image, each encoder against zero-image and shuffled-image
  (graftcache.analysis.findings);
- seed stability repeats every judged comparison on each seed alone (with 4 seeds or more: on each half of the
  seeds) and says whether it gives the same verdict and target top tier (graftcache.analysis.stability).

Given rollouts (graftcache.analysis.rollouts), the offline scores are set against each closed-loop measure
(success and, where the rollouts record them, the graded measures of progress) per cell
(graftcache.analysis.closed_loop: Wilson intervals; Spearman, Kendall tau-b and MMRV over run_ids, each with a 95%
bootstrap interval over each cell's episodes, graftcache.analysis.closed_loop_boot), and the native tower is set
against zero-image on the same episodes (graftcache.analysis.paired_control); each pair of candidate encoders gets a
verdict from paired t intervals offline (over fit seeds) and in closed loop (over fit seed and episode key), agree /
disagree / offline only / closed loop only / neither (graftcache.analysis.pairwise). Results rows that hold one
policy count once (graftcache.analysis.policies). Where the table holds the dose family (`noise-A` controls), each
encoder's dose curve is drawn offline and, given rollouts, in the closed loop, and the finest offline gap the closed
loop confirms is its resolution (graftcache.analysis.dose).

Missing cells are never dropped: they appear as rows with null statistics and a `status`/`note`, and a
verdict that cannot be reached is "insufficient data". Non-finite eval_mse (a diverged fit) counts as invalid.
"""

from __future__ import annotations

from dataclasses import dataclass

import polars as pl

from graftcache.analysis.agreement import (
    PAIRING_SCHEMA,
    TAU_SCHEMA,
    kendall_tau,
    seed_disagreement_counts,
    seed_pairings,
    tau_matrix,
)
from graftcache.analysis.closed_loop import (
    AGREEMENT_SCHEMA,
    CANDIDATES,
    CELL_SCHEMA,
    CELLS_OF,
    CLOSED_LOOP_SCORES,
    MEASURE_COLUMNS,
    STATISTICS,
    WITH_CONTROLS,
    ClosedLoop,
    closed_loop,
    mmrv,
    spearman,
    wilson,
)
from graftcache.analysis.closed_loop_boot import N_BOOT
from graftcache.analysis.control_gaps import CONTROLS_SCHEMA, controls_distance, wrapper_non_neutrality
from graftcache.analysis.dose import DoseCurves, dose_curves
from graftcache.analysis.findings import (
    BEATS,
    BEATS_BOTH,
    NOT_SEPARATED,
    SEPARATED,
    beats_image_controls,
    native_vs_zero_image,
)
from graftcache.analysis.headline import HEADLINE_SCHEMA, ladder_headline
from graftcache.analysis.ladder import PARAMS_COLUMN, Ladder, backbone_ladder, format_params
from graftcache.analysis.looks import FIXED_LEVEL, LOOKS_FILE, Looks, read_looks
from graftcache.analysis.paired_control import (
    CONTROL_SCHEMA,
    NATIVE_BETTER,
    ZERO_IMAGE_BETTER,
    paired_control,
)
from graftcache.analysis.pairwise import (
    A_BETTER,
    AGREE,
    B_BETTER,
    CLOSED_ONLY,
    DISAGREE,
    NEITHER,
    NOT_RESOLVED,
    OFFLINE_ONLY,
    PAIRWISE_SCHEMA,
    SUMMARY_SCHEMA,
    pairwise,
    pairwise_summary,
)
from graftcache.analysis.rollouts import (
    GRADED_MEASURES,
    HIGHER_IS_BETTER,
    MEASURES,
    PAIR_KEY,
    PROVENANCE,
    ROLLOUT_COLUMNS,
    read_rollouts,
)
from graftcache.analysis.scores import (
    DISAGREEMENT_SCHEMA,
    SCORE_LABELS,
    SCORES,
    has_score,
    score_disagreement,
    scored,
)
from graftcache.analysis.stability import HALVES_FROM, STABILITY_SCHEMA, seed_parts, seed_stability
from graftcache.analysis.stats import BASIS_MISSING, SOLID_BASES, BootSettings, tau_b
from graftcache.analysis.summaries import (
    duplicate_rows,
    episode_coverage,
    missing_cells,
    near_tie_band,
    rankings,
    seed_summary,
)
from graftcache.analysis.table import (
    CELL,
    EPISODE_COLUMN,
    GROUP,
    NATIVE_CONTROL,
    NATIVE_GRAFT_CONTROL,
    NOT_ENCODER_CONTROLS,
    PLAIN,
    RECIPE_COLUMNS,
    SHUFFLED_IMAGE,
    ZERO_IMAGE,
    backbone_label,
)
from graftcache.analysis.transfer import (
    COUNT_COLUMNS,
    DOES_NOT_TRANSFER,
    INSUFFICIENT,
    NEAR_TIE,
    SEED_VERDICT_SCHEMA,
    TRANSFERS,
    VERDICT_SCHEMA,
    VERDICTS,
    seed_verdicts,
    transfer_verdicts,
    verdict_counts,
)
from graftcache.errors import GraftcacheError
from graftcache.results import conform

__all__ = [
    "AGREEMENT_SCHEMA", "CANDIDATES", "CELLS_OF", "WITH_CONTROLS", "CELL_SCHEMA", "CLOSED_LOOP_SCORES",
    "CONTROL_SCHEMA", "GRADED_MEASURES", "HIGHER_IS_BETTER",
    "MEASURES", "MEASURE_COLUMNS", "N_BOOT", "NATIVE_BETTER", "PAIR_KEY", "PROVENANCE", "ROLLOUT_COLUMNS",
    "STATISTICS", "ZERO_IMAGE_BETTER", "ClosedLoop", "closed_loop", "mmrv", "paired_control", "read_rollouts",
    "spearman", "wilson", "DoseCurves", "dose_curves", "FIXED_LEVEL", "LOOKS_FILE", "Looks", "read_looks",
    "A_BETTER", "AGREE", "B_BETTER", "CLOSED_ONLY", "DISAGREE", "NEITHER", "NOT_RESOLVED", "OFFLINE_ONLY",
    "PAIRWISE_SCHEMA", "SUMMARY_SCHEMA",
    "pairwise", "pairwise_summary",
    "BEATS", "BEATS_BOTH", "NOT_SEPARATED", "SEPARATED", "beats_image_controls", "native_vs_zero_image",
    "BASIS_MISSING", "CELL", "CONTROLS_SCHEMA", "COUNT_COLUMNS", "DISAGREEMENT_SCHEMA",
    "DOES_NOT_TRANSFER", "EPISODE_COLUMN", "GROUP", "HALVES_FROM", "HEADLINE_SCHEMA", "INSUFFICIENT",
    "NATIVE_CONTROL", "NATIVE_GRAFT_CONTROL",
    "NEAR_TIE", "NOT_ENCODER_CONTROLS", "PAIRING_SCHEMA", "PARAMS_COLUMN", "PLAIN", "RECIPE_COLUMNS",
    "SCORES", "SCORE_LABELS", "SEED_VERDICT_SCHEMA", "SHUFFLED_IMAGE", "SOLID_BASES", "STABILITY_SCHEMA", "TAU_SCHEMA",
    "TRANSFERS",
    "VERDICTS", "VERDICT_SCHEMA", "ZERO_IMAGE", "Analysis", "BootSettings", "Ladder", "analyze",
    "backbone_label", "backbone_ladder", "controls_distance", "duplicate_rows", "episode_coverage",
    "format_params", "has_score", "kendall_tau", "ladder_headline", "missing_cells", "near_tie_band", "rankings",
    "score_disagreement", "scored", "seed_disagreement_counts", "seed_pairings", "seed_parts", "seed_stability",
    "seed_summary", "seed_verdicts",
    "tau_b", "tau_matrix", "transfer_verdicts", "verdict_counts", "wrapper_non_neutrality",
]


@dataclass(frozen=True)
class Analysis:
    """Every table the report and notebook show, computed once from one results table."""

    results: pl.DataFrame  # every SCHEMA column (absent ones null), the chosen score in eval_mse
    ladder: Ladder  # backbones with valid plain rows, smallest first
    score: str  # a SCORES name: what eval_mse holds here
    boot: BootSettings
    band: pl.DataFrame  # seed_summary + rank + top tier, per (backbone, suite, encoder)
    verdicts: pl.DataFrame  # per (suite, pair, direction)
    seed_verdicts: pl.DataFrame  # per (suite, pair, seed, direction)
    stability: pl.DataFrame  # per judged (suite, pair, direction) and part of the seeds: same verdict and tier?
    headline: pl.DataFrame  # per suite: smallest -> largest, and the rung where the ranking breaks
    pairings: pl.DataFrame
    disagreements: pl.DataFrame
    tau: pl.DataFrame  # per (suite, pair)
    wrapper: pl.DataFrame
    controls: pl.DataFrame  # every encoder-level control in the table
    reads_images: pl.DataFrame  # per (backbone, suite): native tower vs pooled zero-image, on every seed
    beats_controls: pl.DataFrame  # per (backbone, suite, encoder): plain graft vs both image controls, every seed
    missing: pl.DataFrame
    scores: pl.DataFrame  # where the MSE and CI-MSE rankings disagree (empty without CI-MSE)
    closed_loop: ClosedLoop | None = None  # offline scores vs rollouts' measures (None: no rollouts given)
    dose: DoseCurves | None = None  # the dose family's curves and resolution (None: no noise-A rows)

    @property
    def small(self) -> str | None:
        """The smallest backbone on the ladder."""
        return self.ladder.backbones[0] if self.ladder.backbones else None

    @property
    def large(self) -> str | None:
        """The largest backbone on the ladder."""
        return self.ladder.backbones[-1] if self.ladder.backbones else None

    @property
    def backbones(self) -> list[str]:
        """Backbones with plain-graft rows: the ladder's, smallest first, then any without a valid MSE by name."""
        have = set(self.band["backbone"].to_list())
        return [b for b in self.ladder.backbones if b in have] + sorted(have - set(self.ladder.backbones))

    @property
    def transfer_gap(self) -> str | None:
        """Why the transfer question cannot be asked (fewer than two backbones), or None."""
        return self.ladder.gap

    @property
    def suites(self) -> list[str]:
        return sorted(set(self.band["suite"].to_list()))

    @property
    def episode_coverage(self) -> tuple[int, int]:
        """(plain-graft cells bootstrapped over episodes too, plain-graft cells with valid rows)."""
        return episode_coverage(self.results)


def analyze(results: pl.DataFrame, *, score: str = "mse", boot: BootSettings = BootSettings(),
            rollouts: pl.DataFrame | None = None, looks: Looks | None = None) -> Analysis:
    """All questions at once, on the table conformed to SCHEMA (results.conform: absent columns null), ranked
    by `score` (a SCORES name); with `rollouts` (read_rollouts: run_id, success, the graded measures and the
    episode key per episode), every closed-loop measure against every offline score too, bootstrapped with
    `boot.seed`; `looks`: the record of the sequential rollout that wrote them (graftcache.analysis.looks).

    Raises GraftcacheError when rows share (backbone, suite, encoder, control, seed) - the table mixes
    recipes (objective, lr, ...) and must be filtered to one before ranking - and when the backbones cannot be
    ordered (graftcache.analysis.ladder)."""
    results = conform(results)
    dup = duplicate_rows(results)
    if len(dup):
        first = dup.row(0, named=True)
        raise GraftcacheError(
            f"{len(dup)} (backbone, suite, encoder, control, seed) keys have several rows, e.g. "
            f"{first['backbone']}/{first['suite']}/{first['encoder']}/{first['control']}"
            f"/seed {first['seed']} "
            f"differing in {', '.join(first['differing']) or 'nothing (duplicate rows)'}: "
            "filter the table to one recipe"
        )
    disagreement = score_disagreement(results)
    # every score, before `scored`
    against = None if rollouts is None else closed_loop(results, rollouts, seed=boot.seed, looks=looks)
    dose = dose_curves(results, rollouts)  # eval_mse, whatever `score` ranks by
    results = scored(results, score)
    ladder = backbone_ladder(results)
    verdicts = transfer_verdicts(results, ladder=ladder, boot=boot)
    per_seed = seed_verdicts(results, ladder=ladder, boot=boot)
    return Analysis(
        results=results,
        ladder=ladder,
        score=score,
        boot=boot,
        band=near_tie_band(results, boot=boot),
        verdicts=verdicts,
        seed_verdicts=per_seed,
        stability=seed_stability(results, verdicts, per_seed, ladder=ladder, boot=boot),
        headline=ladder_headline(verdicts, ladder),
        pairings=seed_pairings(results, ladder=ladder),
        disagreements=seed_disagreement_counts(results, ladder=ladder),
        tau=kendall_tau(results, ladder=ladder),
        wrapper=wrapper_non_neutrality(results),
        controls=controls_distance(results, controls=None, boot=boot),
        reads_images=native_vs_zero_image(results),
        beats_controls=beats_image_controls(results),
        missing=missing_cells(results),
        scores=disagreement,
        closed_loop=against,
        dose=dose,
    )
