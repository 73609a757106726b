"""What the report says: sentences, tables and sections, each built as blocks from one Analysis."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from datetime import UTC, datetime
from pathlib import Path

import polars as pl

from graftcache import analysis as A
from graftcache import results as R
from graftcache.report.document import Alert, Block, Bullets, Heading, Image, Paragraph, Table
from graftcache.report.figures import FIGURES

PROXY_NOTE = (
    "Offline action MSE on held-out episodes is a proxy for closed-loop task success, not a measure of it: "
    "validation MSE is a weak predictor of rollout success, so these rankings say which encoder the frozen "
    "backbone can read best offline, and need rollouts before they are read as success rates."
)
SEED_LEVEL_BOOTSTRAP = "seed-level bootstrap"


# ---------------------------------------------------------------------------------------------- helpers
def _num(x: float | None, fmt: str = ".4g") -> str:
    return "—" if x is None else format(x, fmt)


def _pct(x: float | None) -> str:
    return "—" if x is None else f"{100 * x:+.1f}%"


def _yes(x: bool | None) -> str:
    return "—" if x is None else ("yes" if x else "no")


def _code(text: object) -> str:
    return f"`{text}`" if text else "—"


def _label(name: str) -> str:
    return A.backbone_label(name)


def _direction(source: str, target: str) -> str:
    return f"{_label(source)} → {_label(target)}"


def _in_backbone_order(a: A.Analysis, frame: pl.DataFrame) -> pl.DataFrame:
    """Small backbone first, then large, then others; the frame's own order within a backbone is kept."""
    order = {b: i for i, b in enumerate(a.backbones)}
    key = pl.col("backbone").replace_strict(order, default=len(order), return_dtype=pl.Int64)
    return frame.sort(key, maintain_order=True)


def _counted(n: int, unit: str) -> str:
    return f"{n} {unit}" + ("" if n == 1 else "s")


# ---------------------------------------------------------------------------------------------- sentences
def bootstrap_sentence(a: A.Analysis) -> str:
    """Which bootstrap the top tiers rest on: a table without per-episode MSEs (older versions, other
    tools, a paper) gets a seed-level bootstrap, and the report must say so."""
    have, total = a.episode_coverage
    if total and have == total:
        return (f"Every cell carries per-episode MSEs (`{A.EPISODE_COLUMN}`): the bootstrap resamples seeds, "
                "then held-out episodes within each drawn seed.")
    if not have:
        return (f"{SEED_LEVEL_BOOTSTRAP.capitalize()}: no row carries per-episode MSEs "
                f"(`{A.EPISODE_COLUMN}`), so the bootstrap resamples seeds only and held-out-episode noise "
                "enters only through the spread between seeds.")
    return (f"Per-episode MSEs (`{A.EPISODE_COLUMN}`) cover {have} of {total} cells: comparisons between two "
            f"such cells resample seeds, then episodes; all others use a {SEED_LEVEL_BOOTSTRAP} "
            "(seeds only).")


def transfer_summary(a: A.Analysis) -> str:
    """The paper's count: in how many comparisons (suite x direction) and seed-level cells (suite x
    direction x seed) the ranking transfers, out of those that could be judged, and what the rest were."""
    c = A.verdict_counts(a.verdicts).row(0, named=True)
    s = A.verdict_counts(a.seed_verdicts).row(0, named=True)
    text = (
        f"Across {_counted(len(a.suites), 'suite')} and both directions ({_direction(a.small, a.large)}, "
        f"{_direction(a.large, a.small)}), the ranking transfers in {c['n_transfers']} of {c['n_judged']} "
        f"comparisons (suite × direction) and {s['n_transfers']} of {s['n_judged']} seed-level cells "
        "(suite × direction × seed)."
    )
    rest = [
        f"{what}: {_counted(c[col], 'comparison')}, {_counted(s[col], 'cell')}"
        for what, col in (
            (f"{A.NEAR_TIE} (not a transfer)", A.COUNT_COLUMNS[A.NEAR_TIE]),
            (A.DOES_NOT_TRANSFER, A.COUNT_COLUMNS[A.DOES_NOT_TRANSFER]),
            (f"{A.INSUFFICIENT} (not counted)", A.COUNT_COLUMNS[A.INSUFFICIENT]),
        )
        if c[col] or s[col]
    ]
    return text + (" Other verdicts — " + "; ".join(rest) + "." if rest else "")


def verdict_sentences(a: A.Analysis) -> list[str]:
    """One sentence per suite and direction, the way the paper states a transfer result, with that
    comparison's seed-level count; a suite that cannot be judged gets one sentence for both directions."""
    seeds = {
        (r["suite"], r["source"]): r
        for r in A.verdict_counts(a.seed_verdicts, ("suite", "source")).iter_rows(named=True)
    }
    out: dict[str, None] = {}  # ordered set: the two directions of an unjudgeable suite say the same
    for v in a.verdicts.iter_rows(named=True):
        if v["verdict"] == A.INSUFFICIENT:
            out[f"On {v['suite']}, transfer cannot be judged ({v['verdict']}): {v['note']}."] = None
            continue
        src, dst = _label(v["source"]), _label(v["target"])
        many = "," in v["source_winner"]
        who = f"the {src} winner{'s' if many else ''} ({v['source_winner']})"
        tier = ", ".join(v["target_band"])
        sentence = {
            A.TRANSFERS: f"On {v['suite']}, {who} {'are' if many else 'is'} in {dst}'s top tier: "
            "the ranking transfers.",
            A.NEAR_TIE: f"On {v['suite']}, every shared encoder is in {dst}'s top tier ({tier}): "
            f"a seed-sensitive {A.NEAR_TIE}, so {who} landing in it is not a transfer.",
            A.DOES_NOT_TRANSFER: f"On {v['suite']}, {who} {'are' if many else 'is'} not in {dst}'s top tier "
            f"({tier}): the ranking does not transfer.",
        }[v["verdict"]]
        if v["basis"] not in A.SOLID_BASES:
            sentence += f" [{dst} top tier basis: {v['basis']}]"
        cells = seeds.get((v["suite"], v["source"]))
        if cells and cells["n_judged"]:
            sentence += f" Seed level: {cells['n_transfers']} of {cells['n_judged']} cells transfer."
        out[sentence] = None
    return list(out)


# ---------------------------------------------------------------------------------------------- tables
Row = Mapping[str, object]
Column = tuple[str, Callable[[Row], str]]


def _col(name: str, fmt: Callable[[object], str] = str) -> Callable[[Row], str]:
    """Read one column of a row dict and format it; null -> '—' unless the formatter handles it."""
    return lambda r: "—" if r[name] is None and fmt is str else fmt(r[name])


def _table(frame: pl.DataFrame, columns: tuple[Column, ...]) -> Table:
    """A Table block from a frame and (header, formatter) pairs: the column layout is data, not code."""
    rows = tuple(tuple(f(r) for _, f in columns) for r in frame.iter_rows(named=True))
    return Table(tuple(h for h, _ in columns), rows)


BACKBONE: Column = ("backbone", _col("backbone", _label))
NOTE: Column = ("note", lambda r: r["note"] or "")
DIRECTION: Column = ("direction", lambda r: _direction(r["source"], r["target"]))
TARGET_TIER: Column = ("target top tier", lambda r: ", ".join(r["target_band"] or []) or "—")

MSE_COLUMNS: tuple[Column, ...] = (
    BACKBONE, ("suite", _col("suite")), ("encoder", _col("encoder")), ("rank", _col("rank")),
    ("mean ± std", lambda r: "—" if r["mean"] is None else f"{r['mean']:.4g} ± {_num(r['std'])}"),
    ("n", _col("n")), ("min", _col("min", _num)), ("max", _col("max", _num)),
    ("top tier", _col("in_band", _yes)), ("P(worse than best)", _col("p_worse", lambda x: _num(x, ".3f"))),
    ("basis", _col("basis")),
)
WRAPPER_COLUMNS: tuple[Column, ...] = (
    BACKBONE, ("suite", _col("suite")), ("native tower", _col("native_encoder")),
    ("native MSE (n)", lambda r: f"{_num(r['native_mse'])} ({r['native_n']})"),
    ("native-graft MSE (n)", lambda r: f"{_num(r['native_graft_mse'])} ({r['native_graft_n']})"),
    ("non-neutrality", _col("non_neutrality", _pct)),
    ("seed spread", _col("non_neutrality_seed_std", _pct)), NOTE,
)
CONTROL_COLUMNS: tuple[Column, ...] = (
    BACKBONE, ("suite", _col("suite")), ("encoder", _col("encoder")), ("control", _col("control")),
    ("encoder MSE (n)", lambda r: f"{_num(r['enc_mse'])} ({r['enc_n']})"),
    ("control MSE (n)", lambda r: f"{_num(r['control_mse'])} ({r['control_n']})"),
    ("distance", _col("distance", _pct)), ("P(encoder better)", _col("p_better", lambda x: _num(x, ".3f"))),
    ("within noise", _col("within_noise", _yes)), NOTE,
)
MISSING_COLUMNS: tuple[Column, ...] = (
    BACKBONE, ("suite", _col("suite")), ("encoder", _col("encoder")), ("problem", _col("problem")),
)
PROVENANCE_COLUMNS: tuple[Column, ...] = (
    ("backbone", _col("backbone")), ("suite", _col("suite")), ("encoder", _col("encoder")),
    ("control", _col("control")), ("seed", _col("seed")), ("eval_mse", _col("eval_mse", _num)),
    ("cache key", _col("cache_key", _code)), ("command", _col("command", _code)),
)
SEED_COLUMNS: tuple[Column, ...] = (
    ("suite", _col("suite")), ("seed", _col("seed")), DIRECTION, ("source top-1", _col("source_winner")),
    TARGET_TIER, ("verdict", _col("verdict")), ("basis", _col("basis")), NOTE,
)


def _transfer_columns(a: A.Analysis) -> tuple[Column, ...]:
    tau = dict(a.tau.select("suite", "tau_b").iter_rows())
    dis = {r["suite"]: r for r in a.disagreements.iter_rows(named=True)}
    cells = {
        (r["suite"], r["source"]): r
        for r in A.verdict_counts(a.seed_verdicts, ("suite", "source")).iter_rows(named=True)
    }

    def disagreeing(r: Row) -> str:
        d = dis[r["suite"]]
        unpaired = f" ({d['n_unpaired']} unpaired)" if d["n_unpaired"] else ""
        return f"{d['n_disagree']} of {d['n_pairings']}{unpaired}"

    def seed_level(r: Row) -> str:
        c = cells.get((r["suite"], r["source"]))
        if c is None:
            return "—"
        unjudged = c[A.COUNT_COLUMNS[A.INSUFFICIENT]]
        counted = f"{c['n_transfers']} of {c['n_judged']}"
        return counted + (f" ({unjudged} {A.INSUFFICIENT})" if unjudged else "")

    return (
        ("suite", _col("suite")), DIRECTION, ("source winner", _col("source_winner")), TARGET_TIER,
        ("shared encoders", _col("n_common")), ("seed-level cells transferring", seed_level),
        ("Kendall τb", lambda r: _num(tau.get(r["suite"]), ".2f")),
        ("seed pairings disagreeing on top-1", disagreeing), ("verdict", _col("verdict")), NOTE,
    )


# ---------------------------------------------------------------------------------------------- sections
def header(a: A.Analysis, source: str) -> list[Block]:
    """What the table holds: rows, backbones, suites, encoders, versions, and what it lacks."""
    r = a.results

    def listed(values: object) -> str:
        return ", ".join(sorted(set(values))) or "—"

    have, total = a.episode_coverage
    empty = [c for c in R.SCHEMA if len(r) and r[c].null_count() == len(r)]
    facts = (
        f"Results: `{source}` ({len(r)} rows).",
        "Backbones: " + (", ".join(f"{_label(b)} (`{b}`)" for b in a.backbones) or "none") + ".",
        f"Suites: {listed(a.suites)}.",
        f"Encoders: {listed(a.band['encoder'])}.",
        (f"graftcache versions: {listed(r['graftcache_version'].drop_nulls())}; "
         f"devices: {listed(r['device'].drop_nulls())}."),
        "Per-episode MSEs: " + (
            f"all {total} cells." if have == total
            else f"none ({SEED_LEVEL_BOOTSTRAP}, see Method)." if not have
            else f"{have} of {total} cells ({SEED_LEVEL_BOOTSTRAP} for the rest, see Method)."
        ),
        *([f"Columns without values (absent or all null): {', '.join(empty)}."] if empty else []),
        f"Generated {datetime.now(UTC):%Y-%m-%d %H:%M UTC}.",
    )
    return [Bullets(facts), Paragraph(PROXY_NOTE)]


def random_init_warning(a: A.Analysis) -> list[Block]:
    rand = a.results.filter(pl.col("random_init").fill_null(False))
    if not len(rand):
        return []
    per = rand.group_by("backbone").agg(pl.col("encoder").unique().sort(), n=pl.len()).sort("backbone")
    lead = (
        f"{len(rand)} of {len(a.results)} rows were produced with random-init weights in the encoder or the "
        "backbone: their MSEs say nothing about pretrained representations."
    )
    lines = [f"{_label(b)} (`{b}`): {', '.join(encs)} ({n} rows)" for b, encs, n in per.iter_rows()]
    return [Alert("random-init weights", (lead, *lines))]


def _figure(a: A.Analysis, out: Path, name: str) -> list[Block]:
    draw, caption = FIGURES[name]
    fig = draw(a)
    if fig is None:
        return []
    fig.savefig(out / name, dpi=110)
    return [Image(name, caption)]


def _transfer_section(a: A.Analysis, out: Path) -> list[Block]:
    head = Heading("Does the ranking transfer?")
    if a.transfer_gap:
        return [head, Paragraph(f"The transfer question {a.transfer_gap}, so no verdict is given.")]
    return [
        head, Paragraph(transfer_summary(a)), Bullets(tuple(verdict_sentences(a))),
        _table(a.verdicts, _transfer_columns(a)), *_figure(a, out, "rank_transfer.png"),
    ]


def _mse_section(a: A.Analysis, out: Path) -> list[Block]:
    head = Heading("Offline action MSE per backbone and suite")
    if not len(a.band):
        return [head, Paragraph("No plain-graft rows (control `none`) in the table.")]
    return [head, *_figure(a, out, "mse.png"), _table(_in_backbone_order(a, a.band), MSE_COLUMNS)]


def _seed_section(a: A.Analysis, _: Path) -> list[Block]:
    if a.transfer_gap or not len(a.seed_verdicts):
        return []
    about = (
        "Each comparison repeated on one seed's rows alone: is the source backbone's top-1 at seed s in the "
        "target backbone's top tier at seed s? With one seed per cell that tier rests on the seed's held-out "
        "episodes when rows carry them, and is the exact ties of the best otherwise (basis column)."
    )
    return [Heading("Seed-level agreement"), Paragraph(about), _table(a.seed_verdicts, SEED_COLUMNS)]


def _wrapper_section(a: A.Analysis, _: Path) -> list[Block]:
    about = (
        "(mse(native-graft) − mse(native)) / mse(native): the cost of routing the backbone's own vision "
        "tower through the graft wrapper (pass-through tower + fitted projector); 0 means the wrapper is "
        "neutral."
    )
    body = (
        _table(_in_backbone_order(a, a.wrapper), WRAPPER_COLUMNS) if len(a.wrapper)
        else Paragraph("No `native` or `native-graft` rows in the table.")
    )
    return [Heading("Wrapper non-neutrality"), Paragraph(about), body]


def _controls_section(a: A.Analysis, out: Path) -> list[Block]:
    head = Heading("Controls: does the encoder matter?")
    have = _in_backbone_order(a, a.controls.filter(pl.col("control_n") > 0))
    if not len(have):
        return [head, Paragraph(
            "No encoder-level control rows (zero-image, shuffled-image, pool-HxW, lora)."
        )]
    about = (
        "distance = (mse_control − mse_encoder) / mse_control: the share of the control's error the encoder "
        f"removes. 'within noise' = the encoder is not better than the control at {a.confidence:.0%} "
        "under the seed bootstrap."
    )
    blocks: list[Block] = [head, Paragraph(about)]
    noisy = have.filter(pl.col("control") == A.ZERO_IMAGE, pl.col("within_noise")).select(A.CELL).rows()
    if noisy:
        lines = tuple(f"{_label(b)} · {s} · {e}: the image features add nothing measurable"
                      for b, s, e in noisy)
        blocks.append(Alert("encoders within noise of zero-image", lines))
    blocks += [*_figure(a, out, "controls.png"), _table(have, CONTROL_COLUMNS)]
    if lacking := len(a.controls) - len(have):
        blocks.append(Paragraph(f"{lacking} (encoder, control) pairs have no control rows (not shown)."))
    return blocks


def _missing_section(a: A.Analysis, _: Path) -> list[Block]:
    if not len(a.missing):
        return []
    about = "Gaps in the plain-graft grid; the tables above show them as '—' or 'insufficient data'."
    gaps = _table(_in_backbone_order(a, a.missing), MISSING_COLUMNS)
    return [Heading("Missing cells"), Paragraph(about), gaps]


def _methods_section(a: A.Analysis, _: Path) -> list[Block]:
    small, large = _label(a.small), _label(a.large)
    return [Heading("Method"), Bullets((
        PROXY_NOTE,
        ("Per (backbone, suite, encoder): mean, std (ddof=1), min and max of eval_mse over seeds; "
         "rank 1 = lowest mean, equal means share a rank."),
        (f"Top tier: encoder e is in it unless P(mean_e* > mean_best*) ≥ {a.confidence:.2f} "
         f"over {a.n_boot} bootstrap replicates (seed {a.seed}). With one seed and no per-episode MSEs the "
         "tier is the exact ties of the best (flagged)."),
        bootstrap_sentence(a),
        (f"Transfer, in both directions: the {small} winner(s), among encoders run on both backbones, must "
         f"all be in the {large} top tier ({_direction(a.small, a.large)}), and the {large} winner(s) in the "
         f"{small} top tier ({_direction(a.large, a.small)}). A target top tier holding every shared encoder "
         f"separates nothing, so that comparison is a seed-sensitive '{A.NEAR_TIE}', not a transfer. "
         "Seed-level cells repeat each comparison on one seed's rows; counts ('k of n') leave out "
         f"'{A.INSUFFICIENT}'."),
        "Kendall τb (ties corrected) between the two backbones' mean MSEs over the shared encoders.",
    ))]


def provenance_section(a: A.Analysis, commands: Mapping[str, str] | None) -> list[Block]:
    blocks: list[Block] = [Heading("Provenance: commands and cache keys behind every number")]
    if commands:
        blocks.append(Bullets(tuple(f"{k}: `{v}`" for k, v in commands.items())))
    rows = _in_backbone_order(a, a.results.sort("backbone", "suite", "encoder", "control", "seed"))
    return [*blocks, _table(rows, PROVENANCE_COLUMNS)]


SECTIONS: tuple[Callable[[A.Analysis, Path], list[Block]], ...] = (
    _transfer_section, _mse_section, _seed_section, _wrapper_section, _controls_section, _missing_section,
    _methods_section,
)
