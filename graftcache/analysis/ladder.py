"""Which backbone is small and which is large: the backbones of a table ordered by parameter count, the
ladder every transfer question walks (smallest first).

Each results row records the parameter count of the policy it grafted into (`backbone_params`, counted from
the loaded policy by `graftcache fit`), so tiny and released policies of one backbone sit where their real
sizes put them and a new backbone needs no entry anywhere. A table written before the column (or typed in
from a paper) falls back to the released size on the backbone's spec (`released_params`), and every such
fallback is a note the report prints; a backbone with neither is an error naming it, never a guess.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import pairwise

import polars as pl

from graftcache.analysis.table import backbone_label, check, plain_backbones
from graftcache.errors import GraftcacheError

PARAMS_COLUMN = "backbone_params"


@dataclass(frozen=True)
class Ladder:
    """Backbones with valid plain-graft rows, by ascending parameter count (equal counts: by name)."""

    backbones: tuple[str, ...]
    params: dict[str, int]
    notes: tuple[str, ...]  # how a count was found when not from the rows, and ties broken by name

    @property
    def pairs(self) -> list[tuple[str, str]]:
        """Every (smaller, larger) pair, the smallest backbone's pairs first."""
        b = self.backbones
        return [(b[i], b[j]) for i in range(len(b)) for j in range(i + 1, len(b))]

    @property
    def steps(self) -> list[tuple[str, str]]:
        """Adjacent rungs, (smaller, next larger), bottom to top."""
        return list(pairwise(self.backbones))

    @property
    def gap(self) -> str | None:
        """Why no transfer question can be asked (fewer than two backbones), or None."""
        if len(self.backbones) >= 2:
            return None
        present = ", ".join(backbone_label(b) for b in self.backbones) or "none"
        return f"needs at least two backbones with valid plain-graft rows; present: {present}"


def format_params(n: int) -> str:
    """A parameter count as people write it: 450M, 3.3B, 1.25M."""
    for size, unit in ((1e9, "B"), (1e6, "M"), (1e3, "k")):
        if n >= size:
            return f"{n / size:.3g}{unit}"
    return str(n)


def _count(results: pl.DataFrame, backbone: str) -> tuple[int, str | None]:
    """One backbone's parameter count and the note its finding needs (None: every row records it)."""
    rows = results.filter(pl.col("backbone") == backbone)
    recorded = sorted(set(rows[PARAMS_COLUMN].drop_nulls().to_list())) if PARAMS_COLUMN in rows.columns else []
    if len(recorded) > 1:
        counts = ", ".join(map(str, recorded))
        raise GraftcacheError(f"backbone {backbone}: its rows record {len(recorded)} parameter counts ({counts}), "
                              "so they come from different policies; filter the table to one policy per backbone")
    if recorded:
        lacking = rows[PARAMS_COLUMN].null_count() if PARAMS_COLUMN in rows.columns else 0
        note = (f"{backbone}: {lacking} row(s) without {PARAMS_COLUMN} take the {format_params(recorded[0])} its "
                "other rows record") if lacking else None
        return recorded[0], note
    from graftcache.backbones import registered_spec  # imports the backbone's adapter (torch): old tables only

    spec = registered_spec(backbone)
    if spec is not None and spec.released_params is not None:
        n = spec.released_params
        return n, (f"{backbone}: no row records {PARAMS_COLUMN} (a table from before the column); ordered by the "
                   f"released size, {format_params(n)} (its BackboneSpec's released_params)")
    raise GraftcacheError(f"backbone {backbone}: no row records {PARAMS_COLUMN} and graftcache knows no released size "
                          f"for it; add a {PARAMS_COLUMN} column (the policy's parameter count) to order the backbones")


def backbone_ladder(results: pl.DataFrame) -> Ladder:
    """The table's backbones with valid plain-graft rows, smallest first (see the module docstring)."""
    check(results)
    found = {b: _count(results, b) for b in sorted(plain_backbones(results))}
    params = {b: n for b, (n, _) in found.items()}
    order = tuple(sorted(params, key=lambda b: (params[b], b)))
    notes = [note for _, note in found.values() if note]
    for smaller, larger in pairwise(order):
        if params[smaller] == params[larger]:
            notes.append(f"{smaller} and {larger} have the same parameter count ({params[smaller]}): ordered by name")
    return Ladder(order, params, tuple(notes))
