"""Do the controls say the encoder matters? Wrapper non-neutrality (native vs native-graft) and each
encoder's distance from its zero-image / shuffled-image / pool / lora controls."""

from __future__ import annotations

from collections.abc import Sequence

import polars as pl

from graftcache.analysis.stats import BootSettings, Bootstrap, prob_greater
from graftcache.analysis.summaries import seed_summary
from graftcache.analysis.table import (
    CELL,
    GROUP,
    NATIVE_CONTROL,
    NATIVE_GRAFT_CONTROL,
    NOT_ENCODER_CONTROLS,
    PLAIN,
    SHUFFLED_IMAGE,
    ZERO_IMAGE,
    check,
    control_rows,
)


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
            control_rows(results, control)
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

    out = side(NATIVE_CONTROL, "native").join(side(NATIVE_GRAFT_CONTROL, "native_graft"), on=keys, how="full",
                                              coalesce=True)
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
    boot: BootSettings = BootSettings(),
) -> pl.DataFrame:
    """Does the encoder matter at all? For each encoder and control (rows of that control carry the encoder
    whose features they replace), distance = (mse_control - mse_enc) / mse_control: the fraction of the
    control's error the encoder removes (> 0 encoder helps).

    `p_better` = P(mean_enc* < mean_control*) under the bootstrap; `within_noise` =
    p_better < boot.confidence, i.e. the encoder is not separable from the control (for zero-image: the
    image features add nothing measurable). controls=None takes every encoder-level control in the table
    (pool-HxW, lora, ...). Every requested control gets a row per (backbone, suite, encoder) seen with plain
    or control rows; a missing side gives nulls and a note.
    """
    check(results)
    if controls is None:
        present = set(results["control"].unique().to_list())
        controls = sorted(present - set(NOT_ENCODER_CONTROLS))
    plain = seed_summary(results).filter(pl.col("n_rows") > 0)
    boots = {c: Bootstrap(results, c, boot) for c in (PLAIN, *controls)}
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
                p, rec["basis"] = prob_greater(boots[control], key, boots[PLAIN], key)
                rec["p_better"], rec["within_noise"] = p, p < boot.confidence
            else:
                rec["note"] = (
                    f"no valid {control} rows"
                    if key not in boots[control].cells
                    else "no valid plain-graft rows for this encoder"
                )
            records.append(rec)
    return pl.DataFrame(records, schema=CONTROLS_SCHEMA)
