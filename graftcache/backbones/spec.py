"""What never varies per backbone, declared once as data on its adapter (`BackboneAdapter.spec`), as timm declares a
model's pretrained configuration: how reports write its name, its released size, which lerobot policy type it loads
and which lerobot extra installs it, which policy method makes the images, where the tower and connector sit, where the
LM width is read, how lerobot scales image tokens, which way its flow time runs, how its loss is reduced, whether its
LM and expert can recompute activations, how they can attend, and how many cells share a pass by default. What
differs in behaviour, not data, is a hook on the adapter, each declared once with one signature (`sample_time`,
`_grid_of_config`, `_flow_losses`, `_predict_chunk`, ...).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Literal

from graftcache.errors import BackboneError

#: The fused attention path (torch's scaled_dot_product_attention), which `--attention auto` takes where listed.
FUSED = "sdpa"


@dataclass(frozen=True)
class BackboneSpec:
    """One backbone's constants (see the module docstring)."""

    #: How reports and the README write the backbone ("pi0.5" for pi05; graftcache.analysis.table.backbone_label).
    label: str
    #: The policy method turning a batch into (images, masks) or the model's inputs; grafted, it reads cached features.
    image_method: str
    #: (tower attribute, connector attribute) of the adapter's `_vision_owner`: the graft's two slots.
    vision_slots: tuple[str, str]
    #: Attribute path from the adapter to the LM's embedding width (the projector's output width).
    lm_width: str
    #: Freeze-report groups after the tower and connector: name -> attribute paths from the adapter.
    module_paths: Mapping[str, tuple[str, ...]]
    #: The config field holding the default number of denoising (or decoding) steps; None: the `num_steps` hook.
    steps_field: str | None = None
    #: Preprocessor steps that build the prompt tokens (tokenised once per task unless `prompt_uses_state`).
    token_steps: tuple[str, ...] = ()
    #: The prompt embeds the state (or is built per batch by the policy): tokens are made per batch.
    prompt_uses_state: bool = False
    #: lerobot multiplies image tokens by sqrt(LM width) after the connector (SmolVLA); else by 1.
    scaled_embeddings: bool = False
    #: What the policy's own flow time t is: "noise" (t = 1 at pure noise, graftcache's convention for `time`) or
    #: "data" (t = 1 at the action: graftcache's time is 1 - t); None: no flow time (a token loss).
    flow_time: Literal["noise", "data"] | None = "noise"
    #: `loss` gives one value a sample, so cells may share a backbone pass (fused); False: one mean over the batch.
    loss_per_sample: bool = True
    #: The frozen LM and expert can recompute activations in backward (`_switch_recompute`).
    can_recompute: bool = False
    #: How the frozen LM and expert can attend (graftcache/backbones/attention.py), lerobot's own first: "eager"
    #: (every score matrix materialised) or "sdpa" (torch's fused scaled_dot_product_attention); another than the
    #: first is the `_switch_attention` hook's; `--attention auto` takes sdpa where it is listed.
    attentions: tuple[str, ...] = ("eager",)
    #: Attribute path from the adapter to the module whose forward the training loss calls, which `fit --compile`
    #: compiles (graftcache/backbones/compiled.py); None: no compiled forward.
    compiled_forward: str | None = None
    #: Cells per backbone pass when a request does not say, by device type (graftcache.fit.passes); unlisted: 1.
    cells_per_pass: Mapping[str, int] = field(default_factory=dict)
    #: lerobot's `config.type` of the policy it wraps, which a checkpoint's config.json must name; None: the
    #: registry name (so two adapters, e.g. two graft points, can wrap one lerobot policy type).
    lerobot_type: str | None = None
    #: Approximate parameter count of the released policy (lerobot's docs), for results tables written before rows
    #: recorded `backbone_params`: the analysis orders such a table's backbones by it and says so in the report
    #: (graftcache/analysis/ladder.py). Only the order matters; None: such a table needs the column.
    released_params: int | None = None
    #: The lerobot extra that installs its policy's dependencies (pyproject.toml's lerobot requirement and README's
    #: set-up name each: tests/test_docs.py); None: they are spelled out in pyproject.toml instead (GR00T).
    lerobot_extra: str | None = None
    #: lerobot's internals this backbone's folder reaches (its private functions, methods and attributes), fully
    #: qualified ("lerobot.policies.evo1.modeling_evo1.Evo1Policy._prepare_state"): what a lerobot upgrade must
    #: re-read. tests/backbones/test_lerobot_reaches.py fails on a reach in the folder's code not listed here, on a
    #: listed one no longer used, and on one the installed lerobot lacks. Shared modules of graftcache/backbones/
    #: declare theirs beside their code (`LEROBOT_REACHES`).
    lerobot_reaches: tuple[str, ...] = ()

    def resolve_attention(self, name: str, mode: str) -> str:
        """`auto` -> the fused path where backbone `name` has one, else lerobot's own; an explicit path it lacks is
        refused in one line."""
        paths = self.attentions
        if mode == "auto":
            return FUSED if FUSED in paths else paths[0]
        if mode not in paths:
            raise BackboneError(f"{name}: attention {mode!r} is not one of this backbone's ({', '.join(paths)}: "
                                f"lerobot's own is {paths[0]}); use --attention auto")
        return mode

    def check_execution(self, name: str, *, attention: str, recompute: str, compile: bool) -> None:
        """Refuse, from this data alone (before the policy loads), what backbone `name` cannot run: an attention
        path it lacks, a recompute plan where it cannot recompute (mlp and on both need `can_recompute`; whether it
        has mlp slots is the adapter's, checked when the recompute plan is set), `--compile` without a compiled
        forward."""
        self.resolve_attention(name, attention)
        if recompute in ("mlp", "on") and not self.can_recompute:
            raise BackboneError(f"{name}: no recompute plan {recompute!r} for this backbone; use --recompute off")
        if compile and self.compiled_forward is None:
            raise BackboneError(f"{name}: no compiled forward for this backbone (its spec names none); drop "
                                "--compile")
