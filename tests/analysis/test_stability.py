"""graftcache.analysis.stability (and the report's seed-stability line) on hand-built tables whose answers follow
from tests/helpers/tables.py's worked-out tiers: with no per-episode MSEs, one seed's top tier is the exact ties of
its best encoder."""

from __future__ import annotations

import polars as pl
from helpers.tables import BOTH_WAYS_MSE, exact_p_greater, full_table, ladder_table, plain_rows, table

from graftcache import analysis as A
from graftcache import report
from graftcache.report.sentences import stability_sentences

QUICK = A.BootSettings(n_boot=200)


def _stability(t: pl.DataFrame, boot: A.BootSettings = QUICK) -> tuple[pl.DataFrame, list[str]]:
    a = A.analyze(t, boot=boot)
    return a.stability, stability_sentences(a)


def test_a_suite_every_seed_orders_alike_is_stable_under_each_seed_alone():
    """LADDER_MSE's suite s: every seed orders the encoders as the means do and every tier is the winner alone."""
    st, lines = _stability(ladder_table().filter(pl.col("suite") == "s"))
    assert st.height == 6 * 3  # 3 pairs x 2 directions, each under seeds 0, 1, 2
    assert st["part"].unique(maintain_order=True).to_list() == ["seed 0", "seed 1", "seed 2"]
    assert st["same_verdict"].all() and st["same_tier"].all()
    assert lines == ["Seed stability on s: every verdict and its top tier hold under 3 of 3 seeds alone."]


def test_a_suite_whose_seeds_disagree_says_where_and_how():
    """BOTH_WAYS_MSE's s1: all seeds give pi0.5 the tier {a, b} (SmolVLA -> pi0.5 transfers) and SmolVLA {a}
    (pi0.5's winner b: does not transfer). Seed 0 alone: pi0.5's best is a (1.0 < 1.2), tier {a}; seeds 1 and 2:
    b (1.3 < 1.6, 1.5 < 1.7), tier {b}; SmolVLA's best is a under every seed."""
    st, lines = _stability(table(plain_rows({k: v for k, v in BOTH_WAYS_MSE.items() if k[1] == "s1"})))
    got = {(r["source"], r["part"]): (r["part_verdict"], sorted(r["part_band"]), r["same_verdict"], r["same_tier"])
           for r in st.iter_rows(named=True)}
    assert got == {
        ("smolvla", "seed 0"): (A.TRANSFERS, ["a"], True, False),
        ("smolvla", "seed 1"): (A.DOES_NOT_TRANSFER, ["b"], False, False),
        ("smolvla", "seed 2"): (A.DOES_NOT_TRANSFER, ["b"], False, False),
        ("pi05", "seed 0"): (A.TRANSFERS, ["a"], False, True),
        ("pi05", "seed 1"): (A.DOES_NOT_TRANSFER, ["a"], True, True),
        ("pi05", "seed 2"): (A.DOES_NOT_TRANSFER, ["a"], True, True),
    }
    (line,) = lines
    assert line.startswith("Seed stability on s1: every verdict and its top tier hold under 0 of 3 seeds alone: ")
    assert ("under seed 1, SmolVLA → pi0.5 gives 'does not transfer' with pi0.5's top tier b, all seeds 'transfers' "
            "with a, b") in line
    assert "under seed 0, pi0.5 → SmolVLA gives 'transfers' with SmolVLA's top tier a, all seeds" in line
    assert line.count("under seed") == 4  # the four (direction, seed) parts that differ, and no other


def test_four_seeds_or_more_are_judged_in_halves():
    """From HALVES_FROM seeds on a part is half the seeds (enough for a bootstrap of its own). SmolVLA: a beats b
    under every seed. pi0.5: a beats b under seeds 0 and 1, b beats a under seeds 2 and 3, and over all four seeds
    b is not separated from a (exact bootstrap P well below the confidence): a tier of both, a near-tie band."""
    a_pi, b_pi = [1.0, 1.1, 2.6, 2.7], [2.0, 2.1, 2.0, 2.1]
    assert A.HALVES_FROM == 4 and exact_p_greater(b_pi, a_pi) < 0.8 < A.BootSettings().confidence
    cells = {("smolvla", "s", "a"): [1.0, 1.1, 1.2, 1.3], ("smolvla", "s", "b"): [2.0, 2.1, 2.2, 2.3],
             ("pi05", "s", "a"): a_pi, ("pi05", "s", "b"): b_pi}
    st, lines = _stability(table(plain_rows(cells)), A.BootSettings(n_boot=500))
    up = st.filter(pl.col("source") == "smolvla")
    assert up["verdict"].unique().to_list() == [A.NEAR_TIE]
    assert up.select("part", "part_verdict", "part_band").rows() == [("seeds 0, 1", A.TRANSFERS, ["a"]),
                                                                     ("seeds 2, 3", A.DOES_NOT_TRANSFER, ["b"])]
    assert lines[0].startswith("Seed stability on s: every verdict and its top tier hold under 0 of 2 halves of the "
                               "seeds: under seeds 0, 1, SmolVLA → pi0.5 gives 'transfers'")


def test_one_seed_cannot_measure_stability(tmp_path):
    one = full_table().filter(pl.col("seed") == 0)
    st, lines = _stability(one)
    assert st.is_empty() and list(st.schema) == list(A.STABILITY_SCHEMA)
    assert lines == ["Seed stability cannot be measured: the table holds one seed (0); a rerun with other seeds "
                     "would say whether these verdicts hold."]
    assert lines[0] in report.write_report(one, tmp_path, boot=QUICK).markdown.read_text()


def test_the_report_says_it_in_the_transfer_section(tmp_path):
    md = report.write_report(full_table(), tmp_path, boot=QUICK).markdown.read_text()
    transfer = md[md.index("## Does the ranking transfer?"):md.index("\n## ", md.index("## Does the ranking"))]
    assert "Seed stability: every judged comparison repeated on each seed alone" in transfer
    # libero_object: every seed ranks siglip first on SmolVLA and dinov2-s first on pi0.5, each far from the rest
    stable = "- Seed stability on libero_object: every verdict and its top tier hold under 3 of 3 seeds alone."
    assert stable in transfer
