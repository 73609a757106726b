"""What the report says in words: the proxy caveat, which bootstrap the tiers rest on, the transfer count
and one sentence per comparison, all from one Analysis."""

from __future__ import annotations

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
    direction x seed) the ranking transfers, out of those that could be judged, and what the rest were."""
    c = A.verdict_counts(a.verdicts).row(0, named=True)
    s = A.verdict_counts(a.seed_verdicts).row(0, named=True)
    text = (
        f"Across {_counted(len(a.suites), 'suite')} and both directions ({direction(a.small, a.large)}, "
        f"{direction(a.large, a.small)}), the ranking transfers in {c['n_transfers']} of {c['n_judged']} "
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


def seed_counts(a: A.Analysis) -> dict[tuple[str, str], dict]:
    """(suite, source backbone) -> verdict_counts over that comparison's seed-level cells."""
    counts = A.verdict_counts(a.seed_verdicts, ("suite", "source"))
    return {(r["suite"], r["source"]): r for r in counts.iter_rows(named=True)}


def verdict_sentences(a: A.Analysis) -> list[str]:
    """One sentence per suite and direction, the way the paper states a transfer result, with that
    comparison's seed-level count; a suite that cannot be judged gets one sentence for both directions."""
    seeds = seed_counts(a)
    out: dict[str, None] = {}  # ordered set: the two directions of an unjudgeable suite say the same
    for v in a.verdicts.iter_rows(named=True):
        if v["verdict"] == A.INSUFFICIENT:
            out[f"On {v['suite']}, transfer cannot be judged ({v['verdict']}): {v['note']}."] = None
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
        cells = seeds.get((v["suite"], v["source"]))
        if cells and cells["n_judged"]:
            sentence += f" Seed level: {cells['n_transfers']} of {cells['n_judged']} cells transfer."
        out[sentence] = None
    return list(out)
