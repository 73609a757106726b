"""The report's tables as data: each is a tuple of (header, formatter) columns over one Analysis frame."""

from __future__ import annotations

from collections.abc import Callable, Mapping

import polars as pl

from graftcache import analysis as A
from graftcache.report.document import Table
from graftcache.report.sentences import direction, seed_counts


def num(x: float | None, fmt: str = ".4g") -> str:
    """A number as every table and sentence writes it; null -> '—'."""
    return "—" if x is None else format(x, fmt)


def pct(x: float | None) -> str:
    """A ratio as a signed percentage; null -> '—'."""
    return "—" if x is None else f"{100 * x:+.1f}%"


def _yes(x: bool | None) -> str:
    return "—" if x is None else ("yes" if x else "no")


def _code(text: object) -> str:
    return f"`{text}`" if text else "—"


def in_backbone_order(a: A.Analysis, frame: pl.DataFrame) -> pl.DataFrame:
    """Small backbone first, then large, then others; the frame's own order within a backbone is kept."""
    order = {b: i for i, b in enumerate(a.backbones)}
    key = pl.col("backbone").replace_strict(order, default=len(order), return_dtype=pl.Int64)
    return frame.sort(key, maintain_order=True)


Row = Mapping[str, object]
Column = tuple[str, Callable[[Row], str]]


def col(name: str, fmt: Callable[[object], str] = str) -> Callable[[Row], str]:
    """Read one column of a row dict and format it; null -> '—' unless the formatter handles it."""
    return lambda r: "—" if r[name] is None and fmt is str else fmt(r[name])


def table_block(frame: pl.DataFrame, columns: tuple[Column, ...]) -> Table:
    """A Table block from a frame and (header, formatter) pairs: the column layout is data, not code."""
    rows = tuple(tuple(f(r) for _, f in columns) for r in frame.iter_rows(named=True))
    return Table(tuple(h for h, _ in columns), rows)


BACKBONE: Column = ("backbone", col("backbone", A.backbone_label))
NOTE: Column = ("note", lambda r: r["note"] or "")
DIRECTION: Column = ("direction", lambda r: direction(r["source"], r["target"]))
TARGET_TIER: Column = ("target top tier", lambda r: ", ".join(r["target_band"] or []) or "—")

MSE_COLUMNS: tuple[Column, ...] = (
    BACKBONE, ("suite", col("suite")), ("encoder", col("encoder")), ("rank", col("rank")),
    ("mean ± std", lambda r: "—" if r["mean"] is None else f"{r['mean']:.4g} ± {num(r['std'])}"),
    ("n", col("n")), ("min", col("min", num)), ("max", col("max", num)),
    ("top tier", col("in_band", _yes)), ("P(worse than best)", col("p_worse", lambda x: num(x, ".3f"))),
    ("basis", col("basis")),
)
WRAPPER_COLUMNS: tuple[Column, ...] = (
    BACKBONE, ("suite", col("suite")), ("native tower", col("native_encoder")),
    ("native MSE (n)", lambda r: f"{num(r['native_mse'])} ({r['native_n']})"),
    ("native-graft MSE (n)", lambda r: f"{num(r['native_graft_mse'])} ({r['native_graft_n']})"),
    ("non-neutrality", col("non_neutrality", pct)),
    ("seed spread", col("non_neutrality_seed_std", pct)), NOTE,
)
CONTROL_COLUMNS: tuple[Column, ...] = (
    BACKBONE, ("suite", col("suite")), ("encoder", col("encoder")), ("control", col("control")),
    ("encoder MSE (n)", lambda r: f"{num(r['enc_mse'])} ({r['enc_n']})"),
    ("control MSE (n)", lambda r: f"{num(r['control_mse'])} ({r['control_n']})"),
    ("distance", col("distance", pct)), ("P(encoder better)", col("p_better", lambda x: num(x, ".3f"))),
    ("within noise", col("within_noise", _yes)), NOTE,
)
#: an encoder's weights as its rows record them (encoder_random_init; null: not recorded, or rows disagree)
WEIGHTS = {True: "random-init", False: "real", None: "unknown"}


def _extreme(which: str, name: str) -> Callable[[Row], str]:
    """One side's worst or best seed, with its count of valid rows."""
    return lambda r: f"{num(r[f'{name}_{which}'])} ({r[f'{name}_n']})"


BEATS_COLUMNS: tuple[Column, ...] = (
    BACKBONE, ("suite", col("suite")), ("encoder", col("encoder")),
    ("weights", lambda r: WEIGHTS[r["encoder_random_init"]]),
    ("plain-graft worst seed (n)", _extreme("max", "plain")), ("zero-image best seed (n)", _extreme("min", "zero")),
    ("shuffled-image best seed (n)", _extreme("min", "shuffled")), ("verdict", col("verdict")), NOTE,
)
MISSING_COLUMNS: tuple[Column, ...] = (
    BACKBONE, ("suite", col("suite")), ("encoder", col("encoder")), ("problem", col("problem")),
)
PROVENANCE_COLUMNS: tuple[Column, ...] = (
    ("backbone", col("backbone")), ("suite", col("suite")), ("encoder", col("encoder")),
    ("control", col("control")), ("seed", col("seed")), ("eval_mse", col("eval_mse", num)),
    ("cache key", col("cache_key", _code)), ("command", col("command", _code)),
)
SEED_COLUMNS: tuple[Column, ...] = (
    ("suite", col("suite")), ("seed", col("seed")), DIRECTION, ("source top-1", col("source_winner")),
    TARGET_TIER, ("verdict", col("verdict")), ("basis", col("basis")), NOTE,
)


def _pair_key(a: A.Analysis, r: Row) -> tuple[str, str, str]:
    """(suite, smaller, larger) of a verdict row, how the per-pair frames (tau, pairings) are keyed."""
    rung = a.ladder.backbones.index
    small, large = sorted((r["source"], r["target"]), key=rung)
    return r["suite"], small, large


def transfer_columns(a: A.Analysis) -> tuple[Column, ...]:
    tau = {(r["suite"], r["small"], r["large"]): r["tau_b"] for r in a.tau.iter_rows(named=True)}
    dis = {(r["suite"], r["small"], r["large"]): r for r in a.disagreements.iter_rows(named=True)}
    cells = seed_counts(a)

    def disagreeing(r: Row) -> str:
        d = dis.get(_pair_key(a, r))
        if d is None:
            return "—"
        unpaired = f" ({d['n_unpaired']} unpaired)" if d["n_unpaired"] else ""
        return f"{d['n_disagree']} of {d['n_pairings']}{unpaired}"

    def seed_level(r: Row) -> str:
        c = cells.get((r["suite"], r["source"], r["target"]))
        if c is None:
            return "—"
        unjudged = c[A.COUNT_COLUMNS[A.INSUFFICIENT]]
        counted = f"{c['n_transfers']} of {c['n_judged']}"
        return counted + (f" ({unjudged} {A.INSUFFICIENT})" if unjudged else "")

    return (
        ("suite", col("suite")), DIRECTION, ("source winner", col("source_winner")), TARGET_TIER,
        ("shared encoders", col("n_common")), ("seed-level cells transferring", seed_level),
        ("Kendall τb", lambda r: num(tau.get(_pair_key(a, r)), ".2f")),
        ("seed pairings disagreeing on top-1", disagreeing), ("verdict", col("verdict")), NOTE,
    )


def tau_matrix_block(a: A.Analysis, suite: str) -> Table:
    """One suite's Kendall tau-b between every two backbones, rows and columns in ladder order."""
    names = a.ladder.backbones
    matrix = A.tau_matrix(a.tau, suite, names)
    return Table(("τb", *(A.backbone_label(b) for b in names)),
                 tuple((A.backbone_label(b), *(num(x, ".2f") for x in row)) for b, row in zip(names, matrix)))


def ladder_block(a: A.Analysis) -> Table:
    """The ladder itself: each backbone with the parameter count that placed it."""
    return Table(("rung", "backbone", "parameters"), tuple(
        (str(i + 1), A.backbone_label(b), A.format_params(a.ladder.params[b])) for i, b in enumerate(a.ladder.backbones)
    ))


SCORE_COLUMNS: tuple[Column, ...] = (
    BACKBONE, ("suite", col("suite")), ("top-1 by MSE", col("mse_top1")), ("top-1 by CI-MSE", col("ci_mse_top1")),
    ("same top-1", col("same_top1", _yes)), ("encoders", col("n_common")),
    ("Kendall τb (MSE vs CI-MSE)", col("tau_b", lambda x: num(x, ".2f"))),
    ("rank changes (MSE -> CI-MSE)", lambda r: "; ".join(r["moved"] or []) or "none"),
)
