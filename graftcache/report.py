"""Figures and the written report (report.md + report.html) from a results table.

The report is built once as a list of blocks (heading, paragraph, warning, table, image, bullets) and
rendered twice, so the Markdown and the HTML can never say different things. Figures are drawn on bare
Agg figures (no pyplot state), which keeps report generation headless and lets the notebook display the
very same Figure objects.
"""

from __future__ import annotations

import base64
import html
import re
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import polars as pl
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Patch

from graftcache import analysis as A
from graftcache import results as R
from graftcache.errors import GraftcacheError

PROXY_NOTE = (
    "Offline action MSE on held-out episodes is a proxy for closed-loop task success, not a measure of it: "
    "validation MSE is a weak predictor of rollout success, so these rankings say which encoder the frozen "
    "backbone can read best offline, and need rollouts before they are read as success rates."
)
TITLE = "graftcache report: does the encoder ranking transfer across backbones?"
TIER_COLOR, OTHER_COLOR, WINNER_COLOR = "#1f77b4", "#c7c7c7", "#d62728"
CONTROL_COLORS = {A.ZERO_IMAGE: "#444444", A.SHUFFLED_IMAGE: "#ff7f0e"}
SOLID_BASES = ("seeds", "seeds+episodes")


# ----------------------------------------------------------------------------------------------- blocks
@dataclass(frozen=True)
class Heading:
    text: str
    level: int = 2


@dataclass(frozen=True)
class Paragraph:
    text: str


@dataclass(frozen=True)
class Alert:
    title: str
    lines: tuple[str, ...]


@dataclass(frozen=True)
class Bullets:
    items: tuple[str, ...]


@dataclass(frozen=True)
class Table:
    columns: tuple[str, ...]
    rows: tuple[tuple[str, ...], ...]


@dataclass(frozen=True)
class Image:
    name: str  # file name inside the report folder
    caption: str


Block = Heading | Paragraph | Alert | Bullets | Table | Image


def _inline_html(text: str) -> str:
    """Escape, then turn `code` spans (the only inline markup the report uses) into <code>."""
    return re.sub(r"`([^`]*)`", r"<code>\1</code>", html.escape(text, quote=False))


def _cell_md(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


MD: dict[type, Callable[[Block, Path], str]] = {
    Heading: lambda b, _: f"{'#' * b.level} {b.text}",
    Paragraph: lambda b, _: b.text,
    Alert: lambda b, _: "\n".join([f"> **Warning: {b.title}**", ">", *(f"> - {x}" for x in b.lines)]),
    Bullets: lambda b, _: "\n".join(f"- {x}" for x in b.items),
    Table: lambda b, _: "\n".join(
        [
            f"| {' | '.join(b.columns)} |",
            f"|{'---|' * len(b.columns)}",
            *(f"| {' | '.join(_cell_md(c) for c in r)} |" for r in b.rows),
        ]
    ),
    Image: lambda b, _: f"![{b.caption}]({b.name})\n\n*{b.caption}*",
}


def _img_html(b: Image, root: Path) -> str:
    data = base64.b64encode((root / b.name).read_bytes()).decode()
    return (
        f'<figure><img src="data:image/png;base64,{data}" alt="{html.escape(b.caption)}">'
        f"<figcaption>{_inline_html(b.caption)}</figcaption></figure>"
    )


HTML: dict[type, Callable[[Block, Path], str]] = {
    Heading: lambda b, _: f"<h{b.level}>{_inline_html(b.text)}</h{b.level}>",
    Paragraph: lambda b, _: f"<p>{_inline_html(b.text)}</p>",
    Alert: lambda b, _: (
        f'<div class="warning"><strong>Warning: {_inline_html(b.title)}</strong><ul>'
        + "".join(f"<li>{_inline_html(x)}</li>" for x in b.lines)
        + "</ul></div>"
    ),
    Bullets: lambda b, _: "<ul>" + "".join(f"<li>{_inline_html(x)}</li>" for x in b.items) + "</ul>",
    Table: lambda b, _: (
        "<table><thead><tr>"
        + "".join(f"<th>{_inline_html(c)}</th>" for c in b.columns)
        + "</tr></thead><tbody>"
        + "".join("<tr>" + "".join(f"<td>{_inline_html(c)}</td>" for c in r) + "</tr>" for r in b.rows)
        + "</tbody></table>"
    ),
    Image: _img_html,
}

CSS = """
body{font-family:system-ui,sans-serif;max-width:72rem;margin:2rem auto;padding:0 1rem;line-height:1.45}
table{border-collapse:collapse;margin:1rem 0;font-size:.85rem}
th,td{border:1px solid #ccc;padding:.2rem .45rem} th{background:#f3f3f3}
code{font-size:.8rem;background:#f6f6f6;padding:0 .15rem} img{max-width:100%}
.warning{border:2px solid #d62728;background:#fdecea;padding:.5rem 1rem;margin:1rem 0}
figcaption{font-style:italic}
"""


def render_markdown(blocks: list[Block], root: Path) -> str:
    return "\n\n".join(MD[type(b)](b, root) for b in blocks) + "\n"


def render_html(blocks: list[Block], root: Path, title: str) -> str:
    """One self-contained page: figures are embedded as data URIs, the style sheet is inline."""
    body = "\n".join(HTML[type(b)](b, root) for b in blocks)
    return (
        f'<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8"><title>{html.escape(title)}</title>'
        f"<style>{CSS}</style></head><body>\n{body}\n</body></html>\n"
    )


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


def _in_backbone_order(a: A.Analysis, frame: pl.DataFrame) -> pl.DataFrame:
    """Small backbone first, then large, then others; the frame's own order within a backbone is kept."""
    order = {b: i for i, b in enumerate(a.backbones)}
    key = pl.col("backbone").replace_strict(order, default=len(order), return_dtype=pl.Int64)
    return frame.sort(key, maintain_order=True)


def _plain_values(a: A.Analysis, backbone: str, suite: str, encoder: str) -> list[float]:
    rows = a.results.filter(
        pl.col("control") == A.PLAIN,
        pl.col("backbone") == backbone,
        pl.col("suite") == suite,
        pl.col("encoder") == encoder,
    )
    return [v for v in rows["eval_mse"].to_list() if v is not None and np.isfinite(v)]


def _new_figure(width: float, height: float) -> Figure:
    fig = Figure(figsize=(width, height), layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _grid(n: int, max_cols: int = 4) -> tuple[int, int]:
    cols = min(n, max_cols)
    return -(-n // cols), cols


# ---------------------------------------------------------------------------------------------- figures
def figure_mse(a: A.Analysis) -> Figure | None:
    """Mean eval MSE per encoder (bars), each seed as a dot, the top tier in colour; one panel per
    (backbone, suite). Missing cells are labelled, not skipped. None when there are no plain-graft rows."""
    panels = [(b, s) for b in a.backbones for s in a.suites]
    if not panels:
        return None
    n_enc = a.band.group_by(A.GROUP).len()["len"].max()
    fig = _new_figure(4.2 * len(a.suites), (0.42 * n_enc + 1.3) * len(a.backbones))
    axes = fig.subplots(len(a.backbones), len(a.suites), squeeze=False)
    rng = np.random.default_rng(0)  # dot jitter only
    for (backbone, suite), ax in zip(panels, axes.flat):
        cells = a.band.filter(pl.col("backbone") == backbone, pl.col("suite") == suite).sort(
            "mean", "encoder", nulls_last=True
        )
        for y, r in enumerate(cells.iter_rows(named=True)):
            if r["mean"] is None:
                ax.text(0, y, "  missing", va="center", ha="left", color="0.4", fontsize=8, style="italic")
                continue
            ax.barh(y, r["mean"], color=TIER_COLOR if r["in_band"] else OTHER_COLOR, height=0.6)
            vals = _plain_values(a, backbone, suite, r["encoder"])
            ax.scatter(vals, y + rng.uniform(-0.15, 0.15, len(vals)), s=12, color="black", zorder=3)
        ax.set_yticks(range(len(cells)), cells["encoder"].to_list(), fontsize=8)
        ax.set_ylim(len(cells) - 0.5, -0.5)
        flagged = set(cells["basis"].drop_nulls()) - set(SOLID_BASES) - {"missing"}
        ax.set_title(f"{_label(backbone)} · {suite}" + (" (1 seed)" if flagged else ""), fontsize=9)
        ax.set_xlabel("offline action MSE", fontsize=8)
        ax.tick_params(axis="x", labelsize=7)
    fig.legend(
        handles=[
            Patch(color=TIER_COLOR, label=f"top tier (not separable from best, {a.confidence:.0%})"),
            Patch(color=OTHER_COLOR, label="outside top tier"),
            Line2D([], [], ls="", marker="o", color="black", markersize=4, label="per-seed MSE"),
        ],
        loc="outside lower center",
        ncols=3,
        fontsize=8,
    )
    return fig


def figure_rank_transfer(a: A.Analysis) -> Figure | None:
    """Slope chart per suite: rank on the small backbone (left) vs the large one (right), one line per
    encoder run on both; the small winner in red, the large top tier as filled dots. None without both."""
    if a.transfer_gap or not len(a.verdicts):
        return None
    rows, cols = _grid(len(a.suites))
    n_enc = a.band.group_by(A.GROUP).len()["len"].max()
    fig = _new_figure(3.6 * cols, (0.35 * n_enc + 1.6) * rows)
    axes = fig.subplots(rows, cols, squeeze=False)
    tau = dict(a.tau.select("suite", "tau_b").iter_rows())
    for ax, v in zip(axes.flat, a.verdicts.iter_rows(named=True)):
        suite = v["suite"]
        ranks = {
            b: dict(
                a.band.filter(pl.col("backbone") == b, pl.col("suite") == suite)
                .drop_nulls("rank")
                .select("encoder", "rank")
                .iter_rows()
            )
            for b in (a.small, a.large)
        }
        winners = set((v["small_winner"] or "").split(", ")) - {""}
        tier = set(v["large_band"] or [])
        for enc in sorted(set(ranks[a.small]) & set(ranks[a.large])):
            color = WINNER_COLOR if enc in winners else "0.55"
            ax.plot(
                [0, 1],
                [ranks[a.small][enc], ranks[a.large][enc]],
                color=color,
                lw=2.4 if enc in winners else 1.2,
                zorder=2,
            )
            ax.scatter(
                [1],
                [ranks[a.large][enc]],
                s=36,
                zorder=3,
                color=color,
                facecolors=color if enc in tier else "white",
            )
            ax.scatter([0], [ranks[a.small][enc]], s=36, zorder=3, color=color)
        for x, b, ha in ((-0.06, a.small, "right"), (1.06, a.large, "left")):
            by_rank: dict[int, list[str]] = {}
            for enc, r in ranks[b].items():
                only = "" if enc in ranks[a.large if b == a.small else a.small] else " *"
                by_rank.setdefault(r, []).append(enc + only)
            for r, names in by_rank.items():
                ax.text(x, r, ", ".join(sorted(names)), ha=ha, va="center", fontsize=7)
        top = max([*ranks[a.small].values(), *ranks[a.large].values(), 1])
        ax.set_ylim(top + 0.5, 0.5)
        ax.set_xlim(-0.9, 1.9)
        ax.set_xticks([0, 1], [_label(a.small), _label(a.large)], fontsize=8)
        ax.set_yticks(range(1, top + 1))
        ax.set_ylabel("rank (1 = lowest MSE)", fontsize=8)
        t = "" if tau.get(suite) is None else f", τb = {tau[suite]:.2f}"
        ax.set_title(f"{suite}\n{v['verdict']}{t}", fontsize=9)
    for ax in list(axes.flat)[len(a.verdicts) :]:
        ax.set_visible(False)
    fig.legend(
        handles=[
            Line2D([], [], color=WINNER_COLOR, lw=2.4, label=f"{_label(a.small)} winner"),
            Line2D([], [], ls="", marker="o", color="0.55", label=f"in {_label(a.large)} top tier"),
            Line2D(
                [], [], ls="", marker="o", color="0.55", markerfacecolor="white", label="outside top tier"
            ),
        ],
        loc="outside lower center",
        ncols=3,
        fontsize=8,
        title="* = run on one backbone only",
        title_fontsize=7,
    )
    return fig


def figure_controls(a: A.Analysis) -> Figure | None:
    """Per (backbone, suite): how much of each control's error the encoder removes,
    (mse_control - mse_enc) / mse_control in %, one marker per control; encoders whose MSE is within noise
    of zero-image are labelled in red. None when no control could be compared."""
    c = a.controls.drop_nulls("distance")
    if not len(c):
        return None
    backbones = [b for b in a.backbones if b in set(c["backbone"])]
    suites = sorted(set(c["suite"]))
    n_enc = c.group_by(A.GROUP).agg(pl.col("encoder").n_unique())["encoder"].max()
    fig = _new_figure(4.2 * len(suites), (0.4 * n_enc + 1.4) * len(backbones))
    axes = fig.subplots(len(backbones), len(suites), squeeze=False)
    controls = sorted(set(c["control"]))
    colors = {k: CONTROL_COLORS.get(k, f"C{i + 2}") for i, k in enumerate(controls)}
    for ax, (backbone, suite) in zip(axes.flat, [(b, s) for b in backbones for s in suites]):
        cells = c.filter(pl.col("backbone") == backbone, pl.col("suite") == suite)
        if not len(cells):
            ax.set_visible(False)
            continue
        encs = sorted(set(cells["encoder"]))
        noisy = set(cells.filter(pl.col("control") == A.ZERO_IMAGE, pl.col("within_noise"))["encoder"])
        for i, k in enumerate(controls):
            sub = cells.filter(pl.col("control") == k)
            y = [encs.index(e) + (i - (len(controls) - 1) / 2) * 0.15 for e in sub["encoder"]]
            ax.scatter(100 * sub["distance"].to_numpy(), y, color=colors[k], s=30, zorder=3)
        ax.axvline(0, color="0.3", lw=0.8)
        ax.set_yticks(range(len(encs)), encs, fontsize=8)
        for tick, e in zip(ax.get_yticklabels(), encs):
            tick.set_color(WINNER_COLOR if e in noisy else "black")
        ax.set_ylim(len(encs) - 0.5, -0.5)
        ax.set_xlabel("(control − encoder) / control  [%]", fontsize=8)
        ax.set_title(f"{_label(backbone)} · {suite}", fontsize=9)
    fig.legend(
        handles=[Line2D([], [], ls="", marker="o", color=colors[k], label=k) for k in controls],
        loc="outside lower center",
        ncols=len(controls),
        fontsize=8,
        title="red encoder name = within noise of zero-image",
        title_fontsize=7,
    )
    return fig


FIGURES: dict[str, tuple[Callable[[A.Analysis], Figure | None], str]] = {
    "mse.png": (figure_mse, "Offline action MSE per encoder; dots are seeds, coloured bars the top tier."),
    "rank_transfer.png": (figure_rank_transfer, "Rank of each encoder on the small vs the large backbone."),
    "controls.png": (figure_controls, "Distance of each encoder from its controls (> 0: the encoder helps)."),
}


# ---------------------------------------------------------------------------------------------- sentences
def verdict_sentences(a: A.Analysis) -> list[str]:
    """One sentence per suite, the way the paper states a transfer result."""
    small, large = _label(a.small), _label(a.large)
    out = []
    for v in a.verdicts.iter_rows(named=True):
        if v["verdict"] == A.INSUFFICIENT:
            out.append(f"On {v['suite']}, transfer cannot be judged ({v['verdict']}): {v['note']}.")
            continue
        many = "," in v["small_winner"]
        who = f"the {small} winner{'s' if many else ''} ({v['small_winner']}) {'are' if many else 'is'}"
        flag = "" if v["basis"] in SOLID_BASES else f" [{large} top tier basis: {v['basis']}]"
        if v["verdict"] == A.TRANSFERS:
            out.append(f"On {v['suite']}, {who} in {large}'s top tier: the ranking transfers.{flag}")
        else:
            tier = ", ".join(v["large_band"])
            out.append(
                f"On {v['suite']}, {who} not in {large}'s top tier ({tier}): "
                f"the ranking does not transfer.{flag}"
            )
    return out


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


def _transfer_columns(a: A.Analysis) -> tuple[Column, ...]:
    tau = dict(a.tau.select("suite", "tau_b").iter_rows())
    dis = {r["suite"]: r for r in a.disagreements.iter_rows(named=True)}

    def disagreeing(r: Row) -> str:
        d = dis[r["suite"]]
        unpaired = f" ({d['n_unpaired']} unpaired)" if d["n_unpaired"] else ""
        return f"{d['n_disagree']} of {d['n_pairings']}{unpaired}"

    return (
        ("suite", _col("suite")), (f"{_label(a.small)} winner", _col("small_winner")),
        (f"{_label(a.large)} top tier", lambda r: ", ".join(r["large_band"] or []) or "—"),
        ("shared encoders", _col("n_common")), ("Kendall τb", lambda r: _num(tau.get(r["suite"]), ".2f")),
        ("seed pairings disagreeing on top-1", disagreeing), ("verdict", _col("verdict")), NOTE,
    )


def _seed_columns(a: A.Analysis) -> tuple[Column, ...]:
    return (
        ("suite", _col("suite")), ("seed", _col("seed")), (f"{_label(a.small)} top-1", _col("small_top1")),
        (f"{_label(a.large)} top-1", _col("large_top1")), ("disagree", _col("disagree", _yes)), NOTE,
    )


# ---------------------------------------------------------------------------------------------- sections
def _header(a: A.Analysis, source: str) -> list[Block]:
    r = a.results

    def listed(values: object) -> str:
        return ", ".join(sorted(set(values))) or "—"

    facts = (
        f"Results: `{source}` ({len(r)} rows).",
        "Backbones: " + (", ".join(f"{_label(b)} (`{b}`)" for b in a.backbones) or "none") + ".",
        f"Suites: {listed(a.suites)}.",
        f"Encoders: {listed(a.band['encoder'])}.",
        (f"graftcache versions: {listed(r['graftcache_version'].drop_nulls())}; "
         f"devices: {listed(r['device'].drop_nulls())}."),
        f"Generated {datetime.now(UTC):%Y-%m-%d %H:%M UTC}.",
    )
    return [Bullets(facts), Paragraph(PROXY_NOTE)]


def _random_init_warning(a: A.Analysis) -> list[Block]:
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
        head, Bullets(tuple(verdict_sentences(a))), _table(a.verdicts, _transfer_columns(a)),
        *_figure(a, out, "rank_transfer.png"),
    ]


def _mse_section(a: A.Analysis, out: Path) -> list[Block]:
    head = Heading("Offline action MSE per backbone and suite")
    if not len(a.band):
        return [head, Paragraph("No plain-graft rows (control `none`) in the table.")]
    return [head, *_figure(a, out, "mse.png"), _table(_in_backbone_order(a, a.band), MSE_COLUMNS)]


def _seed_section(a: A.Analysis, _: Path) -> list[Block]:
    if a.transfer_gap or not len(a.pairings):
        return []
    about = (
        f"Seed s on {_label(a.small)} against seed s on {_label(a.large)}, top-1 among the encoders both ran "
        "with that seed; a pairing disagrees when the two top-1 sets share no encoder."
    )
    return [Heading("Seed-level agreement"), Paragraph(about), _table(a.pairings, _seed_columns(a))]


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
         f"over {a.n_boot} bootstrap replicates (seed {a.seed}) resampling seeds, and held-out episodes "
         "when rows carry them. With one seed the tier is the exact ties of the best (flagged)."),
        (f"Transfer: the {small} winner(s), among encoders run on both backbones, must all be in the "
         f"{large} top tier."),
        "Kendall τb (ties corrected) between the two backbones' mean MSEs over the shared encoders.",
    ))]


def _provenance_section(a: A.Analysis, commands: Mapping[str, str] | None) -> list[Block]:
    blocks: list[Block] = [Heading("Provenance: commands and cache keys behind every number")]
    if commands:
        blocks.append(Bullets(tuple(f"{k}: `{v}`" for k, v in commands.items())))
    rows = _in_backbone_order(a, a.results.sort("backbone", "suite", "encoder", "control", "seed"))
    return [*blocks, _table(rows, PROVENANCE_COLUMNS)]


SECTIONS: tuple[Callable[[A.Analysis, Path], list[Block]], ...] = (
    _transfer_section, _mse_section, _seed_section, _wrapper_section, _controls_section, _missing_section,
    _methods_section,
)


# ---------------------------------------------------------------------------------------------- entry points
@dataclass(frozen=True)
class ReportPaths:
    markdown: Path
    html: Path
    figures: tuple[Path, ...]


def write_report(
    results: pl.DataFrame | str | Path,
    out_dir: str | Path,
    *,
    commands: Mapping[str, str] | None = None,
    small: str = A.SMALL,
    large: str = A.LARGE,
    confidence: float = A.CONFIDENCE,
    n_boot: int = A.N_BOOT,
    seed: int = A.BOOT_SEED,
) -> ReportPaths:
    """Analyse a results table (or Parquet path) and write report.md, report.html and PNG figures to out_dir.

    `commands` (name -> command line) are cited at the top of the provenance section, e.g. the sweep and
    report invocations; every row's own `command` and `cache_key` are listed there too.
    """
    source = str(results) if isinstance(results, (str, Path)) else "in-memory table"
    table = R.read(results) if isinstance(results, (str, Path)) else results
    a = A.analyze(table, small=small, large=large, confidence=confidence, n_boot=n_boot, seed=seed)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    for name in FIGURES:  # a rerun must not leave a stale figure the new report no longer shows
        (out / name).unlink(missing_ok=True)
    blocks: list[Block] = [Heading(TITLE, 1), *_random_init_warning(a), *_header(a, source)]
    for section in SECTIONS:
        blocks += section(a, out)
    blocks += _provenance_section(a, commands)
    md, page = out / "report.md", out / "report.html"
    md.write_text(render_markdown(blocks, out), encoding="utf-8")
    page.write_text(render_html(blocks, out, TITLE), encoding="utf-8")
    figures = tuple(out / b.name for b in blocks if isinstance(b, Image))
    return ReportPaths(md, page, figures)


def report_command(results_path: str | Path, out_dir: str | Path, *, command: str | None = None) -> int:
    """`graftcache report RESULTS --out DIR`: write the report, print where it is, return the exit code.

    A missing results file is a GraftcacheError (the CLI prints it as one line); `command` is the exact
    invocation to cite in the report (the CLI passes its argv), defaulting to the canonical form.
    """
    path = Path(results_path)
    if not path.is_file():
        raise GraftcacheError(f"{path}: no results file (run `graftcache sweep` or `graftcache demo` first)")
    paths = write_report(path, out_dir, commands={"report": command or f"graftcache report {path} --out {out_dir}"})
    print(f"report: {paths.markdown}\n        {paths.html}")
    return 0
