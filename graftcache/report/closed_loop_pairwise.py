"""The closed-loop section's pairwise verdicts: which of two candidate encoders is better, offline and in closed
loop, per pair (graftcache.analysis.pairwise), in words and a table, for one measure.

This is the table a user picking an encoder reads: an agreement figure over a cloud of policies says whether
offline scores and the closed loop go together on average, a pair's verdict says whether the encoder that wins
offline also wins in the simulator, and where the episodes spent cannot tell."""

from __future__ import annotations

import polars as pl

from graftcache import analysis as A
from graftcache.report.document import Block, Bullets, Paragraph
from graftcache.report.tables import BACKBONE, NOTE, Column, Row, col, in_backbone_order, table_block

PAIRWISE = (
    "For each pair of candidate encoders A and B (plain grafts): offline, the mean over the fit seeds both have of "
    "eval_mse(A) − eval_mse(B), each seed's two projectors scored on the same eval frames; in closed loop, the mean "
    "over the (fit seed, episode key) pairs both ran of A's {label} minus B's, the same scene, perturbation and step "
    "limit. Each with its paired Student-t interval ({levels}); a side is resolved where its interval excludes 0, and "
    "names the better encoder (lower eval_mse; {side} {label}). The verdict: agree or disagree where both sides are "
    "resolved, offline only or closed loop only where one is, neither where none is."
)


def _better(r: Row, side: str) -> str:
    call = r[side]
    return "—" if call is None else {A.A_BETTER: r["encoder_a"], A.B_BETTER: r["encoder_b"]}.get(call, call)


def _difference(r: Row, side: str, fmt: str, unit: str) -> str:
    d, low, high = r[f"{side}_difference"], r[f"{side}_low"], r[f"{side}_high"]
    if d is None:
        return "—"
    return f"{d:{fmt}}{unit}" + ("" if low is None else f" [{low:{fmt}}, {high:{fmt}}]")


def pairwise_columns(unit: str) -> tuple[Column, ...]:
    """The pairwise table: the pair, each side's paired difference with its interval and call, the verdict."""
    return (
        BACKBONE, ("suite", col("suite")), ("A", col("encoder_a")), ("B", col("encoder_b")),
        ("seeds", col("seeds")), ("offline A − B [95%]", lambda r: _difference(r, "offline", "+.3g", "")),
        ("offline better", lambda r: _better(r, "offline")), ("pairs", col("pairs")),
        ("closed loop A − B [95%]", lambda r: _difference(r, "closed", "+.3g", unit)),
        ("closed loop better", lambda r: _better(r, "closed")), ("verdict", lambda r: r["verdict"] or "—"), NOTE,
    )


def summary_sentence(r: Row, table: pl.DataFrame) -> str:
    """"k of n pairs resolved by both agree" for one (backbone, suite, measure), with the other verdicts' counts."""
    where = f"{A.backbone_label(r['backbone'])} · {r['suite']}"
    counts = table.filter(pl.col("backbone") == r["backbone"], pl.col("suite") == r["suite"])["verdict"]
    rest = ", ".join(f"{int((counts == v).sum())} {v}" for v in (A.OFFLINE_ONLY, A.CLOSED_ONLY, A.NEITHER))
    undecided = counts.null_count()
    n = r["encoder_pairs"]
    return (f"{where}: {r['agree']} of {r['resolved_by_both']} pairs resolved by both agree ({n} pair"
            f"{'s' if n != 1 else ''} of candidate encoders: {rest}"
            + (f", {undecided} without a verdict" if undecided else "") + ").")


def _call_words(r: Row, side: str) -> str:
    """A side's call in words: the better encoder, else why there is none."""
    return f"better: {_better(r, side)}" if r[side] in (A.A_BETTER, A.B_BETTER) else (r[side] or "no call")


def pair_sentence(r: Row, unit: str) -> str:
    """One pair's two sides and verdict in a line (what `demo --closed-loop` prints; the table says it in columns)."""
    return (f"{A.backbone_label(r['backbone'])} · {r['suite']} · {r['encoder_a']} − {r['encoder_b']}: offline "
            f"{_difference(r, 'offline', '+.3g', '')} over {r['seeds']} seeds ({_call_words(r, 'offline')}), "
            f"closed loop {_difference(r, 'closed', '+.3g', unit)} over {r['pairs']} pairs "
            f"({_call_words(r, 'closed')}): {r['verdict'] or 'no verdict'}.")


def pairwise_lines(a: A.Analysis, measure: str, unit: str) -> list[str]:
    """Per (backbone, suite) whose candidate pairs ran paired episodes: the "k of n pairs resolved by both agree"
    sentence, then each pair's line (a command's printout; the report's table has every pair)."""
    table = in_backbone_order(a, a.closed_loop.pairwise.filter(pl.col("measure") == measure))
    rolled = table.group_by("backbone", "suite").agg(pl.col("pairs").max()).filter(pl.col("pairs") > 0)
    table = table.join(rolled.select("backbone", "suite"), on=["backbone", "suite"], how="semi")
    lines = []
    for r in A.pairwise_summary(table).iter_rows(named=True):
        lines.append(summary_sentence(r, table))
        lines += [pair_sentence(p, unit) for p in table.filter(pl.col("backbone") == r["backbone"],
                                                               pl.col("suite") == r["suite"]).iter_rows(named=True)]
    return lines


def looks_sentence(looks: A.Looks) -> str:
    """What a sequential rollout's looks spent and decided, and the error rate its levels hold."""
    last = looks.looks[-1]
    left = "; ".join(f"{x} vs {y} ({A.backbone_label(b)} · {s})" for b, s, x, y in last.unresolved)
    return (f"The closed-loop episodes were added sequentially (`rollout --until-resolved {looks.cap}`): looks of "
            f"{looks.step} episode(s) per task, at most {looks.max_looks}, each adding episodes only to the "
            f"candidate pairs whose closed-loop {looks.measure} interval still held 0; every look's interval is "
            f"taken at {looks.level:.2%} (Bonferroni over the looks), so a pair of equal encoders is called "
            f"resolved with chance at most {looks.error:.0%} whatever look it stopped at. "
            f"{len(looks.looks)} look(s) ran, the last at {last.episodes_per_task} episodes per task; "
            + (f"unresolved after it: {left}." if left else "no pair was left unresolved."))


def pairwise_blocks(a: A.Analysis, measure: str, label: str, unit: str) -> list[Block]:
    """The paragraph, the summary per backbone and suite, and the table, for `measure` (named `label`, `unit`)."""
    table = in_backbone_order(a, a.closed_loop.pairwise.filter(pl.col("measure") == measure))
    if not len(table):
        return [Paragraph("No (backbone, suite) has two candidate encoders: no pair to judge.")]
    side = "higher" if A.HIGHER_IS_BETTER[measure] else "lower"
    summary = A.pairwise_summary(table)
    looks = a.closed_loop.looks
    closed = A.FIXED_LEVEL if looks is None else looks.level
    levels = (f"at {A.FIXED_LEVEL:.0%}" if closed == A.FIXED_LEVEL
              else f"offline at {A.FIXED_LEVEL:.0%}, in closed loop at {closed:.2%}: the sequential looks' level")
    blocks: list[Block] = [Paragraph(PAIRWISE.format(label=label, side=side, levels=levels))]
    if looks is not None:
        blocks.append(Paragraph(looks_sentence(looks)))
    return [*blocks,
            Bullets(tuple(summary_sentence(r, table) for r in summary.iter_rows(named=True))),
            table_block(table, pairwise_columns(unit))]
