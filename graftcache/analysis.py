"""Questions asked of a results table (graftcache.results.SCHEMA), one function each: polars in, polars out.

The paper's question is whether the ranking of vision encoders found on a small frozen backbone (SmolVLA)
transfers to a large one (pi0.5). Seeds are few and offline MSE is noisy, so "the winner" is replaced by a
*top tier*: every encoder whose MSE cannot be separated from the best one's under a bootstrap.

Statistics (stated once here, cited by the report):
- the unit of replication is the seed (projector init + data order); when rows carry per-episode MSEs in
  an optional list column `eval_mse_episodes`, the bootstrap is two-level (seeds, then held-out episodes
  within each drawn seed), otherwise it resamples seeds only;
- encoder e is in the top tier of a (backbone, suite) unless P(mean_e* > mean_best*) >= confidence over
  `n_boot` independent bootstrap replicates of both cells (a one-sided test at `confidence`, 95% by default);
- with a single seed and no episodes the bootstrap is degenerate, so the tier is the exact ties of the best
  mean; such rows are flagged in `basis`;
- every replicate draw comes from a generator seeded by (seed, backbone, suite, encoder), so results are
  deterministic and do not depend on row order.

Missing cells are never dropped: they appear as rows with null statistics and a `status`/`note`, and a
verdict that cannot be reached is "insufficient data". Non-finite eval_mse (a diverged fit) counts as invalid.
"""

from __future__ import annotations

import math
import zlib
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import polars as pl

from graftcache.errors import GraftcacheError
from graftcache.results import SCHEMA

PLAIN = "none"
NATIVE = "native"
NATIVE_GRAFT = "native-graft"
ZERO_IMAGE = "zero-image"
SHUFFLED_IMAGE = "shuffled-image"
NOT_ENCODER_CONTROLS = (PLAIN, NATIVE, NATIVE_GRAFT)

SMALL = "smolvla"
LARGE = "pi05"
BACKBONE_LABELS = {"smolvla": "SmolVLA", "pi05": "pi0.5"}

EPISODE_COLUMN = "eval_mse_episodes"
CONFIDENCE = 0.95
N_BOOT = 2000
BOOT_SEED = 0

TRANSFERS = "transfers"
DOES_NOT_TRANSFER = "does not transfer"
INSUFFICIENT = "insufficient data"

CELL = ["backbone", "suite", "encoder"]
GROUP = ["backbone", "suite"]
RECIPE_COLUMNS = ("policy", "objective", "pool_grid", "steps", "lr", "batch_size", "eval_split_seed")


def backbone_label(name: str) -> str:
    """How the paper writes a backbone name ("pi05" -> "pi0.5"); unknown names pass through."""
    return BACKBONE_LABELS.get(name, name)


def _check(results: pl.DataFrame) -> None:
    """Every SCHEMA column must be there (extra ones, e.g. EPISODE_COLUMN, are allowed)."""
    missing = [c for c in SCHEMA if c not in results.columns]
    if missing:
        raise GraftcacheError(f"results table lacks column(s) {missing}")


def _rows(results: pl.DataFrame, control: str) -> pl.DataFrame:
    """Rows of one control with non-finite eval_mse turned into null (counted as invalid, never averaged)."""
    _check(results)
    mse = pl.col("eval_mse")
    return results.filter(pl.col("control") == control).with_columns(
        eval_mse=pl.when(mse.is_finite()).then(mse).otherwise(None)
    )


def _suites(results: pl.DataFrame) -> list[str]:
    return sorted(_rows(results, PLAIN)["suite"].unique().to_list())


def _backbones(results: pl.DataFrame) -> set[str]:
    return set(_rows(results, PLAIN).drop_nulls("eval_mse")["backbone"].unique().to_list())


def duplicate_rows(results: pl.DataFrame) -> pl.DataFrame:
    """Keys (backbone, suite, encoder, control, seed) held by more than one row, with the recipe columns
    whose values differ among them: such a table mixes recipes and must be filtered before ranking."""
    _check(results)
    keys = [*CELL, "control", "seed"]
    dup = results.group_by(keys).agg(
        n=pl.len().cast(pl.Int64), **{c: pl.col(c).n_unique().cast(pl.Int64) for c in RECIPE_COLUMNS}
    )
    differing = [pl.when(pl.col(c) > 1).then(pl.lit(c)) for c in RECIPE_COLUMNS]
    return (
        dup.filter(pl.col("n") > 1)
        .select(*keys, "n", differing=pl.concat_list(differing).list.drop_nulls())
        .sort(keys)
    )


def seed_summary(results: pl.DataFrame, control: str = PLAIN) -> pl.DataFrame:
    """Mean, std (ddof=1), n, min, max of eval_mse over seeds per (backbone, suite, encoder).

    The grid is every backbone x every (suite, encoder) seen among the control's rows, so an encoder run on
    one backbone only shows up on the other as `status == "missing"` with n == 0 and null statistics.
    status: "ok" (>= 2 valid seeds), "single seed", "no valid eval_mse" (all null/non-finite), "missing".
    """
    rows = _rows(results, control)
    valid = pl.col("eval_mse").is_not_null()
    stats = rows.group_by(CELL).agg(
        n=pl.col("eval_mse").count().cast(pl.Int64),
        n_rows=pl.len().cast(pl.Int64),
        mean=pl.col("eval_mse").mean(),
        std=pl.col("eval_mse").std(ddof=1),
        min=pl.col("eval_mse").min(),
        max=pl.col("eval_mse").max(),
        seeds=pl.col("seed").filter(valid).sort(),
    )
    grid = rows.select("backbone").unique().join(rows.select("suite", "encoder").unique(), how="cross")
    out = grid.join(stats, on=CELL, how="left").with_columns(pl.col("n", "n_rows").fill_null(0))
    n, n_rows = pl.col("n"), pl.col("n_rows")
    status = (
        pl.when(n_rows == 0)
        .then(pl.lit("missing"))
        .when(n == 0)
        .then(pl.lit("no valid eval_mse"))
        .when(n == 1)
        .then(pl.lit("single seed"))
        .otherwise(pl.lit("ok"))
    )
    return (
        out.with_columns(n_invalid=n_rows - n, status=status)
        .select(*CELL, "n", "mean", "std", "min", "max", "seeds", "n_rows", "n_invalid", "status")
        .sort(CELL)
    )


def rankings(results: pl.DataFrame) -> pl.DataFrame:
    """seed_summary plus `rank` per (backbone, suite): 1 = lowest mean MSE, equal means share the lowest
    rank ("min" ranking: 1, 1, 3); missing cells get a null rank. `n_ranked` counts ranked encoders."""
    return (
        seed_summary(results)
        .with_columns(
            rank=pl.col("mean").rank("min").over(GROUP).cast(pl.Int64),
            n_ranked=pl.col("mean").count().over(GROUP).cast(pl.Int64),
        )
        .sort([*GROUP, "rank", "encoder"], nulls_last=True)
    )


@dataclass(frozen=True)
class _Cell:
    """Valid replicates of one cell: seed-level MSEs, and per-seed episode MSEs when every row has them."""

    values: np.ndarray
    episodes: tuple[np.ndarray, ...] | None


def _cells(rows: pl.DataFrame) -> dict[tuple[str, ...], _Cell]:
    rows = rows.drop_nulls("eval_mse")
    has_episodes = EPISODE_COLUMN in rows.columns
    cells: dict[tuple[str, ...], _Cell] = {}
    for key, group in rows.sort("seed").group_by(CELL, maintain_order=True):
        episodes = None
        if has_episodes:
            lists = [np.asarray(v if v is not None else [], dtype=np.float64) for v in group[EPISODE_COLUMN]]
            if all(len(e) and np.isfinite(e).all() for e in lists):
                episodes = tuple(lists)
        cells[tuple(key)] = _Cell(group["eval_mse"].to_numpy().astype(np.float64), episodes)
    return cells


def _rng(seed: int, *key: str) -> np.random.Generator:
    """A generator that depends only on the bootstrap seed and the cell, not on iteration order."""
    return np.random.default_rng(np.random.SeedSequence([seed, zlib.crc32("\x1f".join(key).encode())]))


def _boot_means(cell: _Cell, rng: np.random.Generator, n_boot: int, with_episodes: bool) -> np.ndarray:
    """n_boot bootstrap replicates of the cell's mean MSE: resample seeds, then (optionally) each drawn
    seed's episodes, so both sources of noise widen the distribution."""
    n = len(cell.values)
    pick = rng.integers(0, n, size=(n_boot, n))
    if not with_episodes or cell.episodes is None:
        return cell.values[pick].mean(axis=1)
    per_seed = np.stack(
        [e[rng.integers(0, len(e), size=(n_boot, n, len(e)))].mean(axis=2) for e in cell.episodes]
    )
    return per_seed[pick, np.arange(n_boot)[:, None], np.arange(n)[None, :]].mean(axis=1)


def _basis(n_a: int, n_b: int, episodes: bool) -> str:
    """What a comparison's uncertainty rests on; anything but 'seeds'/'seeds+episodes' is flagged."""
    lo, hi = min(n_a, n_b), max(n_a, n_b)
    if episodes:
        return "seeds+episodes" if lo >= 2 else "episodes (single seed)"
    if lo >= 2:
        return "seeds"
    return "exact ties only (single seed)" if hi == 1 else "seeds (one side single seed)"


class _Bootstrap:
    """Bootstrap replicates per cell, drawn once and reused for every comparison that involves the cell."""

    def __init__(self, results: pl.DataFrame, control: str, n_boot: int, seed: int) -> None:
        self.cells = _cells(_rows(results, control))
        self.tag, self.n_boot, self.seed = control, n_boot, seed
        self._cache: dict[tuple[tuple[str, ...], bool], np.ndarray] = {}

    def means(self, key: tuple[str, ...], with_episodes: bool) -> np.ndarray:
        if (key, with_episodes) not in self._cache:
            rng = _rng(self.seed, self.tag, *key)
            self._cache[key, with_episodes] = _boot_means(self.cells[key], rng, self.n_boot, with_episodes)
        return self._cache[key, with_episodes]

    def has_episodes(self, key: tuple[str, ...]) -> bool:
        return self.cells[key].episodes is not None


def _prob_greater(
    a: _Bootstrap, ka: tuple[str, ...], b: _Bootstrap, kb: tuple[str, ...]
) -> tuple[float, str]:
    """P(mean_a* > mean_b*) over paired-by-index independent replicates, and the comparison's basis."""
    episodes = a.has_episodes(ka) and b.has_episodes(kb)
    p = float(np.mean(a.means(ka, episodes) > b.means(kb, episodes)))
    return p, _basis(len(a.cells[ka].values), len(b.cells[kb].values), episodes)


def near_tie_band(
    results: pl.DataFrame, *, confidence: float = CONFIDENCE, n_boot: int = N_BOOT, seed: int = BOOT_SEED
) -> pl.DataFrame:
    """rankings plus the top tier per (backbone, suite).

    Columns added: `best` (lowest mean; alphabetical first among exact ties), `p_worse` =
    P(mean_enc* > mean_best*) under the bootstrap (null for the best itself and for missing cells),
    `in_band` = p_worse < confidence (null when the cell is missing), `basis` (see module docstring).
    """
    ranks = rankings(results)
    boot = _Bootstrap(results, PLAIN, n_boot, seed)
    records = []
    for (backbone, suite), group in ranks.group_by(GROUP, maintain_order=True):
        ranked = group.drop_nulls("mean").sort("mean", "encoder")
        best = ranked["encoder"][0] if len(ranked) else None
        for enc in group["encoder"]:
            rec = {
                "backbone": backbone,
                "suite": suite,
                "encoder": enc,
                "best": best,
                "p_worse": None,
                "in_band": None,
                "basis": "missing",
            }
            key = (backbone, suite, enc)
            if key in boot.cells and best is not None:
                kb = (backbone, suite, best)
                p, rec["basis"] = _prob_greater(boot, key, boot, kb)
                rec["p_worse"], rec["in_band"] = (None, True) if enc == best else (p, p < confidence)
            records.append(rec)
    band = pl.DataFrame(
        records,
        schema={
            **dict.fromkeys(CELL, pl.String),
            "best": pl.String,
            "p_worse": pl.Float64,
            "in_band": pl.Boolean,
            "basis": pl.String,
        },
    )
    return ranks.join(band, on=CELL, how="left", maintain_order="left")


def _common_encoders(
    results: pl.DataFrame, suite: str, small: str, large: str
) -> tuple[list[str], str | None]:
    """Encoders with valid rows on both backbones for a suite, and a note naming the ones left out."""
    valid = _rows(results, PLAIN).drop_nulls("eval_mse").filter(pl.col("suite") == suite)
    have = {b: set(valid.filter(pl.col("backbone") == b)["encoder"].to_list()) for b in (small, large)}
    common = sorted(have[small] & have[large])
    only = [
        f"{e} (only {backbone_label(b)})"
        for b, o in ((small, large), (large, small))
        for e in sorted(have[b] - have[o])
    ]
    return common, ("left out, not on both backbones: " + ", ".join(only)) if only else None


def two_backbone_gap(results: pl.DataFrame, small: str = SMALL, large: str = LARGE) -> str | None:
    """Why no transfer question can be asked of this table (a backbone without valid plain rows), or None."""
    have = _backbones(results)
    lacking = [backbone_label(b) for b in (small, large) if b not in have]
    if not lacking:
        return None
    present = ", ".join(backbone_label(b) for b in sorted(have)) or "none"
    return f"needs two backbones ({backbone_label(small)} and {backbone_label(large)}); present: {present}"


VERDICT_SCHEMA = {
    "suite": pl.String,
    "small_backbone": pl.String,
    "large_backbone": pl.String,
    "small_winner": pl.String,
    "large_winner": pl.String,
    "large_band": pl.List(pl.String),
    "n_common": pl.Int64,
    "verdict": pl.String,
    "basis": pl.String,
    "note": pl.String,
}


def transfer_verdicts(
    results: pl.DataFrame,
    *,
    small: str = SMALL,
    large: str = LARGE,
    confidence: float = CONFIDENCE,
    n_boot: int = N_BOOT,
    seed: int = BOOT_SEED,
) -> pl.DataFrame:
    """Per suite: is the small backbone's winner in the large backbone's top tier?

    Only encoders with data on both backbones are compared (the others are named in `note`), since a
    winner can only transfer within a shared set. Exact ties for first on the small backbone are all
    winners (joined by ", ") and the ranking transfers only if every one of them is in the large top tier.
    Fewer than two shared encoders, or a missing backbone, give "insufficient data" with the reason in `note`.
    `basis` lists the comparison bases on the large backbone (flags single-seed tiers).
    """
    records = []
    need = two_backbone_gap(results, small, large)
    for suite in _suites(results):
        rec = {"suite": suite, "small_backbone": small, "large_backbone": large, "verdict": INSUFFICIENT}
        common, note = ([], need) if need else _common_encoders(results, suite, small, large)
        rec["n_common"], rec["note"] = len(common), note
        if not need and len(common) < 2:
            rec["note"] = "; ".join(x for x in (f"{len(common)} encoder(s) on both backbones", note) if x)
        if len(common) >= 2:
            sub = results.filter(
                pl.col("suite") == suite,
                pl.col("backbone").is_in([small, large]),
                pl.col("encoder").is_in(common),
            )
            band = near_tie_band(sub, confidence=confidence, n_boot=n_boot, seed=seed)
            on_small = band.filter(pl.col("backbone") == small)
            on_large = band.filter(pl.col("backbone") == large).sort("mean", "encoder")
            winners = on_small.filter(pl.col("rank") == 1)["encoder"].sort().to_list()
            tier = on_large.filter(pl.col("in_band"))["encoder"].to_list()
            rec.update(
                small_winner=", ".join(winners),
                large_winner=", ".join(on_large.filter(pl.col("rank") == 1)["encoder"].sort().to_list()),
                large_band=tier,
                verdict=TRANSFERS if set(winners) <= set(tier) else DOES_NOT_TRANSFER,
                basis=", ".join(sorted(set(on_large["basis"].to_list()))),
            )
        records.append(rec)
    return pl.DataFrame(records, schema=VERDICT_SCHEMA)


def _top1(scores: dict[str, float]) -> set[str]:
    low = min(scores.values())
    return {e for e, v in scores.items() if v == low}


PAIRING_SCHEMA = {
    "suite": pl.String,
    "seed": pl.Int64,
    "small_top1": pl.String,
    "large_top1": pl.String,
    "n_common": pl.Int64,
    "disagree": pl.Boolean,
    "note": pl.String,
}


def seed_pairings(results: pl.DataFrame, *, small: str = SMALL, large: str = LARGE) -> pl.DataFrame:
    """Seed-level cells: seed s on the small backbone vs seed s on the large one, per suite.

    Top-1 is taken among the encoders that have seed s on both backbones; `disagree` is True when the two
    top-1 sets share no encoder (exact ties count as agreeing if any tied encoder is shared). A seed present
    on one backbone only, or fewer than two shared encoders, gives a row with null `disagree` and a note.
    """
    need = two_backbone_gap(results, small, large)
    if need:
        return pl.DataFrame([{"suite": s, "note": need} for s in _suites(results)], schema=PAIRING_SCHEMA)
    valid = _rows(results, PLAIN).drop_nulls("eval_mse")
    records = []
    for suite in _suites(results):
        by_backbone = {
            b: {
                (s, e): v
                for s, e, v in valid.filter(pl.col("suite") == suite, pl.col("backbone") == b)
                .select("seed", "encoder", "eval_mse")
                .iter_rows()
            }
            for b in (small, large)
        }
        seeds = {b: {s for s, _ in by_backbone[b]} for b in (small, large)}
        for s in sorted(seeds[small] | seeds[large]):
            rec = {"suite": suite, "seed": s}
            scores = {b: {e: v for (ss, e), v in by_backbone[b].items() if ss == s} for b in (small, large)}
            common = sorted(set(scores[small]) & set(scores[large]))
            rec["n_common"] = len(common)
            if s not in seeds[small] or s not in seeds[large]:
                lacking = small if s not in seeds[small] else large
                rec["note"] = f"seed {s} not run on {backbone_label(lacking)}"
            elif len(common) < 2:
                rec["note"] = f"{len(common)} encoder(s) with seed {s} on both backbones"
            else:
                top = {b: _top1({e: scores[b][e] for e in common}) for b in (small, large)}
                rec.update(
                    small_top1=", ".join(sorted(top[small])),
                    large_top1=", ".join(sorted(top[large])),
                    disagree=top[small].isdisjoint(top[large]),
                )
            records.append(rec)
    return pl.DataFrame(records, schema=PAIRING_SCHEMA)


def seed_disagreement_counts(
    results: pl.DataFrame, *, small: str = SMALL, large: str = LARGE
) -> pl.DataFrame:
    """Per suite: how many seed pairings were comparable, how many disagree on top-1, how many could not
    be paired (`n_unpaired`), and the disagreeing fraction (null when nothing was comparable)."""
    pairs = seed_pairings(results, small=small, large=large)
    d = pl.col("disagree")
    return (
        pairs.group_by("suite")
        .agg(
            n_pairings=d.count().cast(pl.Int64),
            n_disagree=d.sum().cast(pl.Int64),
            n_unpaired=d.null_count().cast(pl.Int64),
        )
        .with_columns(
            fraction_disagree=pl.when(pl.col("n_pairings") > 0)
            .then(pl.col("n_disagree") / pl.col("n_pairings"))
            .otherwise(None)
        )
        .sort("suite")
    )


def tau_b(x: Sequence[float], y: Sequence[float]) -> float | None:
    """Kendall's tau-b (ties corrected): sum sign(dx)sign(dy) / sqrt(#pairs untied in x * #pairs untied in y).

    None when fewer than two items or when either side is all ties (the statistic is undefined).
    """
    x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    i, j = np.triu_indices(len(x), 1)
    sx, sy = np.sign(x[i] - x[j]), np.sign(y[i] - y[j])
    denom = math.sqrt(float(np.count_nonzero(sx)) * float(np.count_nonzero(sy)))
    return float((sx * sy).sum() / denom) if denom else None


def kendall_tau(results: pl.DataFrame, *, small: str = SMALL, large: str = LARGE) -> pl.DataFrame:
    """Per suite: Kendall tau-b between the two backbones' mean MSEs over the encoders present on both
    (`n_common`); null with a note when it cannot be computed."""
    schema = {"suite": pl.String, "n_common": pl.Int64, "tau_b": pl.Float64, "note": pl.String}
    need = two_backbone_gap(results, small, large)
    summary = seed_summary(results)
    records = []
    for suite in _suites(results):
        rec = {"suite": suite, "n_common": 0, "note": need}
        if not need:
            common, rec["note"] = _common_encoders(results, suite, small, large)
            means = {
                b: dict(
                    summary.filter(pl.col("backbone") == b, pl.col("suite") == suite)
                    .select("encoder", "mean")
                    .iter_rows()
                )
                for b in (small, large)
            }
            rec["n_common"] = len(common)
            rec["tau_b"] = tau_b([means[small][e] for e in common], [means[large][e] for e in common])
            if rec["tau_b"] is None:
                why = "fewer than two shared encoders" if len(common) < 2 else "one backbone's means all tie"
                rec["note"] = "; ".join(x for x in (why, rec["note"]) if x)
        records.append(rec)
    return pl.DataFrame(records, schema=schema)


def wrapper_non_neutrality(results: pl.DataFrame, *, by_suite: bool = True) -> pl.DataFrame:
    """How much the graft wrapper alone costs: (mse(native-graft) - mse(native)) / mse(native).

    Both sides are means over their seeds (the native control is usually one deterministic eval);
    `non_neutrality_seed_std` is std(native-graft seeds) / mse(native), the spread of that ratio over seeds.
    0 means the wrapper is neutral; > 0 means the pass-through tower + projector loses information.
    Per (backbone, suite), or per backbone over all suites with by_suite=False. A side without rows gives
    nulls and a note.
    """
    keys = GROUP if by_suite else ["backbone"]
    mse = pl.col("eval_mse")

    def side(control: str, name: str) -> pl.DataFrame:
        return (
            _rows(results, control)
            .group_by(keys)
            .agg(
                **{
                    f"{name}_encoder": pl.col("encoder").unique().sort().str.join(", "),
                    f"{name}_mse": mse.mean(),
                    f"{name}_std": mse.std(ddof=1),
                    f"{name}_n": mse.count().cast(pl.Int64),
                }
            )
        )

    out = side(NATIVE, "native").join(side(NATIVE_GRAFT, "native_graft"), on=keys, how="full", coalesce=True)
    out = out.with_columns(pl.col("native_n", "native_graft_n").fill_null(0))
    ok = (pl.col("native_mse") > 0) & pl.col("native_graft_mse").is_not_null()
    note = (
        pl.when(pl.col("native_n") == 0)
        .then(pl.lit("no valid native rows"))
        .when(pl.col("native_graft_n") == 0)
        .then(pl.lit("no valid native-graft rows"))
        .when(pl.col("native_mse") <= 0)
        .then(pl.lit("native MSE is 0"))
    )
    return (
        out.with_columns(
            non_neutrality=pl.when(ok).then(
                (pl.col("native_graft_mse") - pl.col("native_mse")) / pl.col("native_mse")
            ),
            non_neutrality_seed_std=pl.when(ok).then(pl.col("native_graft_std") / pl.col("native_mse")),
            note=note,
        )
        .select(
            *keys,
            "native_encoder",
            "native_mse",
            "native_n",
            "native_graft_mse",
            "native_graft_n",
            "non_neutrality",
            "non_neutrality_seed_std",
            "note",
        )
        .sort(keys)
    )


CONTROLS_SCHEMA = {
    **dict.fromkeys(CELL, pl.String),
    "control": pl.String,
    "enc_mse": pl.Float64,
    "enc_n": pl.Int64,
    "control_mse": pl.Float64,
    "control_n": pl.Int64,
    "distance": pl.Float64,
    "p_better": pl.Float64,
    "within_noise": pl.Boolean,
    "basis": pl.String,
    "note": pl.String,
}


def controls_distance(
    results: pl.DataFrame,
    *,
    controls: Sequence[str] | None = (ZERO_IMAGE, SHUFFLED_IMAGE),
    confidence: float = CONFIDENCE,
    n_boot: int = N_BOOT,
    seed: int = BOOT_SEED,
) -> pl.DataFrame:
    """Does the encoder matter at all? For each encoder and control (rows of that control carry the encoder
    whose features they replace), distance = (mse_control - mse_enc) / mse_control: the fraction of the
    control's error the encoder removes (> 0 encoder helps).

    `p_better` = P(mean_enc* < mean_control*) under the bootstrap; `within_noise` = p_better < confidence,
    i.e. the encoder is not separable from the control (for zero-image: the image features add nothing
    measurable). controls=None takes every encoder-level control in the table (pool-HxW, lora, ...).
    Every requested control gets a row per (backbone, suite, encoder) seen with plain or control rows;
    a missing side gives nulls and a note.
    """
    _check(results)
    if controls is None:
        present = set(results["control"].unique().to_list())
        controls = sorted(present - set(NOT_ENCODER_CONTROLS))
    plain = seed_summary(results).filter(pl.col("n_rows") > 0)
    boots = {c: _Bootstrap(results, c, n_boot, seed) for c in (PLAIN, *controls)}
    sums = {c: seed_summary(results, c).filter(pl.col("n_rows") > 0) for c in controls}
    cells = pl.concat([plain.select(CELL), *(s.select(CELL) for s in sums.values())]).unique().sort(CELL)
    stats = {
        c: {tuple(r[:3]): r[3:] for r in s.select(*CELL, "mean", "n").iter_rows()}
        for c, s in {PLAIN: plain, **sums}.items()
    }
    records = []
    for key in cells.iter_rows():
        enc_mse, enc_n = stats[PLAIN].get(key, (None, 0))
        for control in controls:
            ctl_mse, ctl_n = stats[control].get(key, (None, 0))
            rec = dict(
                zip(CELL, key),
                control=control,
                enc_mse=enc_mse,
                enc_n=enc_n,
                control_mse=ctl_mse,
                control_n=ctl_n,
            )
            if key in boots[PLAIN].cells and key in boots[control].cells:
                if ctl_mse > 0:
                    rec["distance"] = (ctl_mse - enc_mse) / ctl_mse
                p, rec["basis"] = _prob_greater(boots[control], key, boots[PLAIN], key)
                rec["p_better"], rec["within_noise"] = p, p < confidence
            else:
                rec["note"] = (
                    f"no valid {control} rows"
                    if key not in boots[control].cells
                    else "no valid plain-graft rows for this encoder"
                )
            records.append(rec)
    return pl.DataFrame(records, schema=CONTROLS_SCHEMA)


def missing_cells(results: pl.DataFrame) -> pl.DataFrame:
    """Every gap in the plain-graft grid, one row per problem: a (backbone, suite, encoder) with no rows,
    rows with null/non-finite eval_mse, and seeds run for other encoders of the same (backbone, suite) but
    not for this one."""
    summary = seed_summary(results)
    seeds = summary.group_by(GROUP).agg(
        all_seeds=pl.col("seeds").list.explode(keep_nulls=False, empty_as_null=False).unique().sort()
    )
    records = []
    for row in summary.join(seeds, on=GROUP, how="left").iter_rows(named=True):
        where = {k: row[k] for k in CELL}
        if row["status"] == "missing":
            records.append({**where, "problem": "no plain-graft rows"})
            continue
        if row["n_invalid"]:
            records.append(
                {**where, "problem": f"{row['n_invalid']} row(s) with null or non-finite eval_mse"}
            )
        lacking = sorted(set(row["all_seeds"]) - set(row["seeds"] or []))
        if lacking and row["n"]:
            records.append({**where, "problem": "missing seed(s) " + ", ".join(map(str, lacking))})
    return pl.DataFrame(records, schema={**dict.fromkeys(CELL, pl.String), "problem": pl.String})


@dataclass(frozen=True)
class Analysis:
    """Every table the report and notebook show, computed once from one results table."""

    results: pl.DataFrame
    small: str
    large: str
    confidence: float
    n_boot: int
    seed: int
    band: pl.DataFrame  # seed_summary + rank + top tier, per (backbone, suite, encoder)
    verdicts: pl.DataFrame
    pairings: pl.DataFrame
    disagreements: pl.DataFrame
    tau: pl.DataFrame
    wrapper: pl.DataFrame
    controls: pl.DataFrame  # every encoder-level control in the table
    missing: pl.DataFrame

    @property
    def backbones(self) -> list[str]:
        """Backbones with plain-graft rows, small and large first, then any others by name."""
        have = set(self.band["backbone"].to_list())
        return [b for b in (self.small, self.large) if b in have] + sorted(have - {self.small, self.large})

    @property
    def transfer_gap(self) -> str | None:
        """Why the transfer question cannot be asked (fewer than two backbones), or None."""
        return two_backbone_gap(self.results, self.small, self.large)

    @property
    def suites(self) -> list[str]:
        return sorted(set(self.band["suite"].to_list()))


def analyze(
    results: pl.DataFrame,
    *,
    small: str = SMALL,
    large: str = LARGE,
    confidence: float = CONFIDENCE,
    n_boot: int = N_BOOT,
    seed: int = BOOT_SEED,
) -> Analysis:
    """All questions at once. Raises GraftcacheError when rows share (backbone, suite, encoder, control,
    seed) - the table mixes recipes (objective, lr, ...) and must be filtered to one before ranking."""
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
    boot = {"confidence": confidence, "n_boot": n_boot, "seed": seed}
    pair = {"small": small, "large": large}
    return Analysis(
        results=results,
        **pair,
        **boot,
        band=near_tie_band(results, **boot),
        verdicts=transfer_verdicts(results, **pair, **boot),
        pairings=seed_pairings(results, **pair),
        disagreements=seed_disagreement_counts(results, **pair),
        tau=kendall_tau(results, **pair),
        wrapper=wrapper_non_neutrality(results),
        controls=controls_distance(results, controls=None, **boot),
        missing=missing_cells(results),
    )
