#!/usr/bin/env python
"""Eager against fused attention (`fit --attention eager|sdpa`): step time, inference time and what a step keeps.

    python benchmarks/bench_attention.py [--backbones pi05,pi0,pi0_fast,smolvla] [--dtypes auto,fp32]
                                         [--batch-size 8] [--repeats 3] [--rounds 3] [--threads 2]
                                         [--json benchmarks/results/bench_attention_cpu.json]

Per backbone with two attention paths (graftcache/backbones/attention.py; tiny, random init: a step's cost does not
depend on what the weights learned) and compute dtype, it times a grafted fit step (forward and backward of the
policy's loss on cached features, fixed draws) and the predicted chunk (the policy's sampler), with each path,
interleaved over `--rounds` so that both see the same machine load, and prints the medians, the eager/fused ratio and
the bytes autograd saves for backward (graftcache.fit.step_bytes.saved_bytes). Then the attention alone at the
released geometry (pi0.5: 8 heads of 256 over one key head, SmolVLA: 15 heads of 64 over 5 key heads, at LIBERO's
sequence lengths), forward and backward, through lerobot's eager functions and graftcache's fused ones: the released
policies' full steps take minutes a step on a CPU, whose time goes to the MLPs (the share of a joint layer's forward
FLOPs the attention matmuls take is printed beside it). Everything is measured in one run; the machine line names the
CPU and whether it computes bf16 in hardware (avx512_bf16).
"""

from __future__ import annotations

import argparse
import functools
import json
import statistics
import time
from collections.abc import Callable
from pathlib import Path

import torch
from common import machine

from graftcache.backbones import load_backbone
from graftcache.backbones.attention import EAGER, FUSED
from graftcache.backbones.tiny import TinyBuild
from graftcache.fit.step_bytes import saved_bytes
from graftcache.graft import GraftProjector, feature_key
from graftcache.runtime import autocast, resolve_compute_dtype, resolve_dtype

ENC_DIM = 768  # SigLIP-B's width, the features a graft projects
TASK = "put the bowl on the plate"
#: Released attention shapes at LIBERO's recipe (devtools.released: two 256 px cameras, chunk 50). pi0.5: three image
#: slots of 16x16 tokens (the third an always-masked empty camera), a 200-token prompt, 50 action tokens; SmolVLA:
#: three slots of 8x8 tokens, a 48-token prompt, one state token, 50 action tokens.
RELEASED = {
    "pi0.5": dict(heads=8, kv_heads=1, head_dim=256, prefix=3 * 256 + 200, suffix=50, width=2048, mlp=16384,
                  expert_width=1024, expert_mlp=4096),
    "SmolVLA": dict(heads=15, kv_heads=5, head_dim=64, prefix=3 * 64 + 48 + 1, suffix=50, width=960, mlp=2560,
                    expert_width=720, expert_mlp=2048),
}


def cpu_flags() -> str:
    """Whether this CPU reports avx512_bf16 (bf16 in hardware: what `--compute-dtype auto` resolves by)."""
    flags = next((ln for ln in Path("/proc/cpuinfo").read_text().splitlines() if ln.startswith("flags")), "")
    return f"avx512_bf16 {'yes' if 'avx512_bf16' in flags.split() else 'no'}"


def median_interleaved(fns: dict[str, Callable[[], object]], repeats: int, rounds: int) -> dict[str, float]:
    """Median seconds of each `fns` entry: `rounds` rounds, each timing every entry `repeats` times in turn (after
    one untimed call each), so a change in the machine's load falls on every entry alike."""
    times: dict[str, list[float]] = {k: [] for k in fns}
    for fn in fns.values():
        fn()
    for _ in range(rounds):
        for key, fn in fns.items():
            for _ in range(repeats):
                t0 = time.perf_counter()
                fn()
                times[key].append(time.perf_counter() - t0)
    return {k: statistics.median(v) for k, v in times.items()}


def tiny_case(name: str, batch_size: int, dtype: torch.dtype, repeats: int, rounds: int) -> dict:
    """Step and inference seconds and saved bytes of one tiny grafted backbone, with each attention path."""
    from devtools.released import unit_stats

    adapter = load_backbone(name, "tiny", dataset_stats=unit_stats(), tiny=TinyBuild())
    torch.manual_seed(0)
    adapter.graft(GraftProjector(ENC_DIM, adapter.lm_width))
    g = torch.Generator().manual_seed(0)
    tokens = adapter.token_grid[0] * adapter.token_grid[1]
    raw = {**{feature_key(k): torch.randn(batch_size, tokens, ENC_DIM, generator=g) for k in adapter.camera_keys},
           "observation.state": torch.randn(batch_size, adapter.state_dim, generator=g),
           "action": torch.randn(batch_size, adapter.chunk_size, adapter.action_dim, generator=g),
           "action_is_pad": torch.zeros(batch_size, adapter.chunk_size, dtype=torch.bool), "task": [TASK] * batch_size}
    batch = adapter.prepare(raw)
    noise = adapter.sample_noise(batch_size, g)
    flow_time = torch.rand(batch_size, generator=g) * 0.9 + 0.05
    device = adapter.device

    def step(mode: str) -> None:
        adapter.set_attention(mode)
        adapter.policy.train()
        adapter.projector.zero_grad(set_to_none=True)
        with autocast(device, dtype):
            loss = adapter.loss(batch, noise, flow_time).mean()
        loss.backward()

    @torch.no_grad()
    def infer(mode: str) -> None:
        adapter.set_attention(mode)
        with autocast(device, dtype):
            adapter.predict(batch, noise)

    fns = {f"{what} {mode}": functools.partial(fn, mode) for what, fn in (("step", step), ("inference", infer))
           for mode in adapter.spec.attentions}
    seconds = median_interleaved(fns, repeats, rounds)
    saved = {}
    for mode in adapter.spec.attentions:
        adapter.set_attention(mode)
        saved[mode] = saved_bytes(adapter, raw, batch_size, dtype)
    return {"seconds": seconds, "saved_bytes": saved, "lerobot_attention": adapter.spec.attentions[0]}


class _Heads(torch.nn.Module):
    """What the eager and fused functions read of an attention module (its grouping; the fused mark)."""

    def __init__(self, heads: int, kv_heads: int) -> None:
        super().__init__()
        self.num_attention_heads, self.num_key_value_heads = heads, kv_heads
        self.num_key_value_groups = heads // kv_heads


def released_attention(family: str, batch_size: int, dtype: torch.dtype, repeats: int, rounds: int) -> dict:
    """Forward and backward seconds of one layer's joint attention at `family`'s released shapes: lerobot's eager
    function against graftcache's fused one, the prefix-LM mask (prefix sees the prefix, the suffix sees all)."""
    from lerobot.policies.smolvla.smolvlm_with_expert import SmolVLMWithExpertModel
    from transformers.models.gemma import modeling_gemma

    from graftcache.backbones.paligemma import FUSED_MARK, GemmaAttentionForward
    from graftcache.backbones.smolvla.adapter import _fused

    s = RELEASED[family]
    h, kv, d, length = s["heads"], s["kv_heads"], s["head_dim"], s["prefix"] + s["suffix"]
    g = torch.Generator().manual_seed(0)
    allowed = torch.ones(batch_size, length, length, dtype=torch.bool)
    allowed[:, : s["prefix"], s["prefix"]:] = False
    module = _Heads(h, kv)
    if family == "pi0.5":  # [B, heads, L, D] in, additive [B, 1, L, L] mask, as modeling_pi05's joint layer calls it
        shapes = [(batch_size, h, length, d), (batch_size, kv, length, d), (batch_size, kv, length, d)]
        mask = torch.where(allowed[:, None], 0.0, -2.3819763e38)
        fused_forward = GemmaAttentionForward(modeling_gemma.eager_attention_forward)
        setattr(module, FUSED_MARK, True)
        paths = {EAGER: lambda q, k, v: modeling_gemma.eager_attention_forward(module, q, k, v, mask, d**-0.5)[0],
                 FUSED: lambda q, k, v: fused_forward(module, q, k, v, mask, d**-0.5)[0]}
    else:  # [B, L, heads, D] in, a bool [B, L, L] mask, as smolvlm_with_expert's layers call it
        shapes = [(batch_size, length, h, d), (batch_size, length, kv, d), (batch_size, length, kv, d)]
        paths = {EAGER: lambda q, k, v: SmolVLMWithExpertModel.eager_attention_forward(module, allowed, batch_size, d,
                                                                                      q, k, v),
                 FUSED: lambda q, k, v: _fused(module, allowed, batch_size, d, q, k, v)}
    qkv = [torch.randn(*shape, generator=g).to(dtype).requires_grad_() for shape in shapes]

    def run(path: Callable, backward: bool) -> None:
        if backward:
            path(*qkv).float().square().mean().backward()
        else:
            with torch.no_grad():
                path(*qkv)

    fns = {f"{what} {mode}": functools.partial(run, path, what == "forward+backward")
           for what in ("forward+backward", "forward") for mode, path in paths.items()}
    seconds = median_interleaved(fns, repeats, rounds)
    lp, ls = s["prefix"], s["suffix"]
    attention_flops = 4 * length * length * h * d
    dense = (lp * (2 * s["width"] * (h + kv) * d + 3 * s["width"] * s["mlp"])
             + ls * (2 * s["expert_width"] * (h + kv) * d + 3 * s["expert_width"] * s["expert_mlp"])) * 2
    return {"seconds": seconds, "length": length, "attention_flop_share": attention_flops / (attention_flops + dense)}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--backbones", default="pi05,pi0,pi0_fast,smolvla")
    p.add_argument("--dtypes", default="auto,fp32", help="compute dtypes (auto: as a fit resolves it here)")
    p.add_argument("--batch-size", type=int, default=8)
    p.add_argument("--released-batch-size", type=int, default=2)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--json", type=Path, default=None)
    a = p.parse_args()
    torch.set_num_threads(a.threads)
    print(f"machine: {machine()}; {cpu_flags()}")
    report: dict = {"machine": machine(), "cpu_flags": cpu_flags(), "batch_size": a.batch_size, "tiny": {},
                    "released_attention": {}}
    for dtype_name in a.dtypes.split(","):
        resolved = resolve_compute_dtype(dtype_name, "cpu")
        dtype = resolve_dtype(resolved)
        for name in a.backbones.split(","):
            r = tiny_case(name, a.batch_size, dtype, a.repeats, a.rounds)
            report["tiny"][f"{name} {resolved}"] = r
            sec, saved = r["seconds"], r["saved_bytes"]
            step, infer = (f"eager {sec[f'{w} eager'] * 1e3:.1f} ms / sdpa {sec[f'{w} sdpa'] * 1e3:.1f} ms = "
                           f"{sec[f'{w} eager'] / sec[f'{w} sdpa']:.2f}x" for w in ("step", "inference"))
            print(f"tiny {name} ({resolved}, batch {a.batch_size}, lerobot's own: {r['lerobot_attention']}): step "
                  f"{step}; inference {infer}; saved for backward {saved[EAGER] / 2**20:.1f} / "
                  f"{saved[FUSED] / 2**20:.1f} MiB")
        for family in RELEASED:
            r = released_attention(family, a.released_batch_size, dtype, a.repeats, a.rounds)
            report["released_attention"][f"{family} {resolved}"] = r
            sec = r["seconds"]
            print(f"released {family} attention ({resolved}, batch {a.released_batch_size}, {r['length']} tokens): "
                  f"forward+backward eager {sec['forward+backward eager'] * 1e3:.1f} ms / sdpa "
                  f"{sec['forward+backward sdpa'] * 1e3:.1f} ms = "
                  f"{sec['forward+backward eager'] / sec['forward+backward sdpa']:.2f}x; forward eager "
                  f"{sec['forward eager'] * 1e3:.1f} ms / sdpa {sec['forward sdpa'] * 1e3:.1f} ms = "
                  f"{sec['forward eager'] / sec['forward sdpa']:.2f}x; attention matmuls "
                  f"{r['attention_flop_share']:.1%} of a joint layer's forward FLOPs")
    if a.json is not None:
        a.json.write_text(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
