"""What the report says in words: the proxy caveat, which bootstrap the tiers rest on, the transfer count
and one sentence per comparison, all from one Analysis."""

from __future__ import annotations

import polars as pl

from graftcache import analysis as A

PROXY_NOTE = (
    "Offline action MSE on held-out episodes is a proxy for closed-loop task success, not a measure of it: "
    "validation MSE is a weak predictor of rollout success, so these rankings say which encoder the frozen "
    "backbone can read best offline, and need rollouts before they are read as success rates."
)
SEED_LEVEL_BOOTSTRAP = "seed-level bootstrap"


def direction(source: str, target: str) -> str:
    return f"{A.backbone_label(source)} → {A.backbone_label(target)}"


def _counted(n: int, unit: str) -> str:
    return f"{n} {unit}" + ("" if n == 1 else "s")


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
    direction x seed) the ranking transfers, out of those that could be judged, and what the rest were.
    With more than two backbones the directions are both of every pair on the ladder."""
    c = A.verdict_counts(a.verdicts).row(0, named=True)
    s = A.verdict_counts(a.seed_verdicts).row(0, named=True)
    n = len(a.ladder.backbones)
    directions = (
        f"both directions ({direction(a.small, a.large)}, {direction(a.large, a.small)})" if n == 2
        else f"both directions of every pair of the {n} backbones ({n * (n - 1)} directions)"
    )
    text = (
        f"Across {_counted(len(a.suites), 'suite')} and {directions}, the ranking transfers in "
        f"{c['n_transfers']} of {c['n_judged']} comparisons (suite × direction) and {s['n_transfers']} of "
        f"{s['n_judged']} seed-level cells (suite × direction × seed)."
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


def seed_counts(a: A.Analysis) -> dict[tuple[str, str, str], dict]:
    """(suite, source backbone, target backbone) -> verdict_counts over that comparison's seed-level cells."""
    counts = A.verdict_counts(a.seed_verdicts, ("suite", "source", "target"))
    return {(r["suite"], r["source"], r["target"]): r for r in counts.iter_rows(named=True)}


def verdict_sentences(a: A.Analysis) -> list[str]:
    """One sentence per suite and direction, the way the paper states a transfer result, with that
    comparison's seed-level count; a suite that cannot be judged gets one sentence for both directions."""
    seeds = seed_counts(a)
    out: dict[str, None] = {}  # ordered set: the two directions of an unjudgeable suite say the same
    for v in a.verdicts.iter_rows(named=True):
        if v["verdict"] == A.INSUFFICIENT:
            pair = "" if len(a.ladder.backbones) == 2 else f" between {_pair(v['source'], v['target'])}"
            out[f"On {v['suite']}, transfer{pair} cannot be judged ({v['verdict']}): {v['note']}."] = None
            continue
        src, dst = A.backbone_label(v["source"]), A.backbone_label(v["target"])
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
        cells = seeds.get((v["suite"], v["source"], v["target"]))
        if cells and cells["n_judged"]:
            sentence += f" Seed level: {cells['n_transfers']} of {cells['n_judged']} cells transfer."
        out[sentence] = None
    return list(out)


def by_halves(a: A.Analysis) -> bool:
    """Whether seed stability judged halves of the seeds (A.HALVES_FROM seeds or more), not each seed alone."""
    return bool(len(a.stability)) and a.stability["part"][0].startswith("seeds ")


def stability_sentences(a: A.Analysis) -> list[str]:
    """Per suite, the seed-stability line: under how many parts of the seeds (each seed alone, or each half) every
    judged comparison keeps its verdict and its target top tier (graftcache.analysis.stability), and each change."""
    st = a.stability
    if not len(st):
        seeds = sorted(set(a.results.filter(pl.col("control") == A.PLAIN)["seed"].to_list()))
        held = f"one seed ({seeds[0]})" if len(seeds) == 1 else "no judged comparison"
        return [f"Seed stability cannot be measured: the table holds {held}; a rerun with other seeds would say "
                "whether these verdicts hold."]
    units = ("half of the seeds", "halves of the seeds") if by_halves(a) else ("seed alone", "seeds alone")
    out = []
    for suite in sorted(set(st["suite"].to_list())):
        rows = st.filter(pl.col("suite") == suite)
        parts = rows["part"].unique(maintain_order=True).to_list()
        open_ = [p for p in parts if rows.filter(pl.col("part") == p)["same_verdict"].null_count()]
        judged = [p for p in parts if p not in open_]
        held = [p for p in judged if rows.filter(pl.col("part") == p).select(
            pl.col("same_verdict").all() & pl.col("same_tier").all()).item()]
        text = (f"Seed stability on {suite}: every verdict and its top tier hold under {len(held)} of "
                f"{len(judged)} {units[len(judged) != 1]}")
        changes = [
            f"under {r['part']}, {direction(r['source'], r['target'])} gives '{r['part_verdict']}' with "
            f"{A.backbone_label(r['target'])}'s top tier {_tier(sorted(r['part_band']))}, all seeds "
            f"'{r['verdict']}' with {_tier(sorted(r['target_band']))}"
            for r in rows.filter(~(pl.col("same_verdict") & pl.col("same_tier"))).iter_rows(named=True)
        ]
        if open_:
            text += f" ({len(open_)} could not be judged: {', '.join(open_)})"
        out.append(text + (": " + "; ".join(changes) if changes else "") + ".")
    return out


def _pair(x: str, y: str) -> str:
    """Two backbones, as an unordered pair (the two directions of an unjudgeable pair say the same)."""
    return " and ".join(A.backbone_label(b) for b in sorted((x, y)))


def _tier(names: list[str] | None) -> str:
    return ", ".join(names or []) or "—"


HEADLINE_OPENERS = {
    A.TRANSFERS: "is in the largest one's ({large}) top tier ({tier}): the ranking transfers from the bottom of "
                 "the ladder to its top.",
    A.DOES_NOT_TRANSFER: "is not in the largest one's ({large}) top tier ({tier}): the ranking does not transfer "
                         "from the bottom of the ladder to its top.",
    A.NEAR_TIE: "lands in the largest one's ({large}) top tier, but that tier holds every shared encoder ({tier}): "
                f"a {A.NEAR_TIE}, not a transfer.",
}


def headline_sentences(a: A.Analysis) -> list[str]:
    """Per suite, the ladder's two answers: does the smallest backbone's winner land in the largest one's top
    tier, and at which rung (a backbone and the next larger one) does the ranking first fail to transfer?"""
    out = []
    for h in a.headline.iter_rows(named=True):
        small, large = A.backbone_label(h["smallest"]), A.backbone_label(h["largest"])
        if h["verdict"] == A.INSUFFICIENT:
            first = (f"On {h['suite']}, the smallest backbone ({small}) and the largest ({large}) cannot be compared "
                     f"({A.INSUFFICIENT}).")
        else:
            winner = f"the smallest backbone's ({small}) winner ({h['smallest_winner']})"
            first = f"On {h['suite']}, {winner} " + HEADLINE_OPENERS[h["verdict"]].format(
                large=large, tier=_tier(h["largest_top_tier"]))
        rungs = "; ".join(f"{direction(x, y)}: {v}" for (x, y), v in zip(a.ladder.steps, h["steps"]))
        if h["break_at"]:
            x, y = h["break_at"].split(" -> ")
            where = f"the ranking breaks at {direction(x, y)}"
        else:
            where = "the ranking breaks at no rung that could be judged"
        below = " below it" if h["break_at"] else ""
        unjudged = f" ({_counted(h['open_rungs'], 'rung')}{below} could not be judged)" if h["open_rungs"] else ""
        out.append(f"{first} Rung by rung ({rungs}): {where}{unjudged}.")
    return out


def score_sentence(a: A.Analysis) -> str:
    """How often MSE and CI-MSE pick different winners, over the (backbone, suite) cells ranked by both."""
    judged = a.scores.drop_nulls("same_top1")
    differ = judged.filter(~pl.col("same_top1"))
    moved = a.scores.filter(pl.col("moved").list.len() > 0)
    return (f"Ranked by {A.SCORE_LABELS['mse']} and by {A.SCORE_LABELS['ci-mse']}, the top-1 encoder differs in "
            f"{len(differ)} of {len(judged)} (backbone, suite) cells, and some encoder changes rank in "
            f"{len(moved)}. This report ranks by {A.SCORE_LABELS[a.score]} (`--score {a.score}`).")
