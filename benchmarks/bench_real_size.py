#!/usr/bin/env python
"""What the cache buys at real size: one flow step and one predict of full-size SmolVLA and pi0.5, from
cached features and online from pixels.

    python benchmarks/bench_real_size.py [--device cpu|cuda] [--compute-dtype auto|bf16|fp32]
        [--backbones smolvla,pi05] [--batches 1,4] [--repeats 5] [--hub DIR] [--out results.json]
        [--only load]

The backbones are random-init at the released geometry (devtools.released: SmolVLM2-500M,
PaliGemma gemma_2b + gemma_300m expert), written as lerobot writes a released policy into a HF hub cache
(`--hub`, reused when present) and loaded by hub id as `--policy org/name` loads them; the cost of a step
does not depend on what the weights learned. Per backbone and batch size, median wall time, peak RSS and
peak CUDA memory of:
- online step: decode each sample's episode (graftcache.datasets, pyav) and take its frame, the ungrafted
  policy's own vision path on the pixels (resize, tower, connector), the flow loss, backward through LM and
  expert, AdamW on the connector;
- cached step: the grafted policy's flow step on features already in memory (the native tower's grid at
  the LM's token grid: SmolVLA 64 x 768, pi0.5 256 x 1152, fp16 like a cache), AdamW on the projector;
- predict: the denoised chunk (the policy's default steps), from pixels and from cached features;
and the ratios cached / online. Also the load (graftcache.backbones.lean_load) and graft (weights hash) peaks;
`--only load` measures just load, graft and reset, with the peak RSS against the checkpoint's bytes. A full
pi0.5 step takes ~10 minutes on a CPU: pi0.5 runs on CPU only with
--cpu-pi05. Needs only graftcache on PYTHONPATH beside lerobot 0.6.1 and its pins (lerobot 0.6.1's pi0.5
does not run under transformers 5.17: create_causal_mask() lost `cache_position`).
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import resource
import time
from collections.abc import Callable
from pathlib import Path

os.environ.setdefault("HF_HUB_OFFLINE", "1")

import numpy as np  # noqa: E402
import torch  # noqa: E402
from common import DEFAULT_DATASET, machine, median_seconds, warm_page_cache  # noqa: E402

from devtools.released import BUILDERS, LIBERO, built_here, hub_cache  # noqa: E402
from graftcache.backbones import get_backbone, load_backbone  # noqa: E402
from graftcache.backbones.surgery import freeze_all_but  # noqa: E402
from graftcache.datasets import open_dataset  # noqa: E402
from graftcache.graft import GraftProjector, feature_key  # noqa: E402
from graftcache.runtime import (  # noqa: E402
    autocast,
    resolve_compute_dtype,
    resolve_device,
    resolve_dtype,
    set_main_threads,
)

DEFAULT_HUB = Path.home() / ".cache" / "graftcache" / "bench-real-size-hub"


class Memory:
    """Peak RSS (VmHWM, reset through /proc/self/clear_refs where the kernel allows it, else the process
    peak) and peak CUDA memory of one phase."""

    def __init__(self, device: torch.device) -> None:
        self.device = device

    def reset(self) -> None:
        try:
            Path("/proc/self/clear_refs").write_text("5")
        except OSError:
            pass
        if self.device.type == "cuda":
            torch.cuda.reset_peak_memory_stats(self.device)

    def peaks(self) -> dict[str, float | None]:
        try:
            status = Path("/proc/self/status").read_text().splitlines()
            line = next(ln for ln in status if ln.startswith("VmHWM:"))
            rss = int(line.split()[1]) * 1024
        except (OSError, StopIteration):
            rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
        cuda = torch.cuda.max_memory_allocated(self.device) if self.device.type == "cuda" else None
        return {"peak_rss_gb": rss / 1e9, "peak_cuda_gb": None if cuda is None else cuda / 1e9}


class Frames:
    """Random dataset frames as raw policy batches: low-dim from the table, pixels decoded per sample."""

    def __init__(self, dataset: Path, chunk: int, seed: int = 0) -> None:
        self.source = open_dataset(dataset)
        table = self.source.lowdim()
        self.episode = table["episode_index"].to_numpy()
        self.frame = table["frame_index"].to_numpy()
        self.state = torch.from_numpy(np.stack(table["state"].to_numpy()).astype(np.float32))
        self.action = torch.from_numpy(np.stack(table["action"].to_numpy()).astype(np.float32))
        self.task = [self.source.meta.tasks[t] for t in table["task_index"].to_numpy()]
        self.chunk = chunk
        self.rng = np.random.default_rng(seed)

    def lowdim(self, rows: np.ndarray) -> dict:
        """State, the action chunk from each row (padded past the episode's end) and task strings."""
        steps = np.minimum(rows[:, None] + np.arange(self.chunk), len(self.episode) - 1)
        pad = torch.from_numpy(self.episode[steps] != self.episode[rows][:, None])  # masked in the loss
        return {"observation.state": self.state[rows], "action": self.action[torch.from_numpy(steps)],
                "action_is_pad": pad, "task": [self.task[r] for r in rows]}

    def pixels(self, rows: np.ndarray, cams: dict[str, str]) -> dict[str, torch.Tensor]:
        """Policy camera key -> [B, 3, H, W] in [0, 1], each sample's episode decoded for its frame."""
        out: dict[str, list] = {key: [] for key in cams}
        for row in rows:
            decoded = self.source.decode_episode(int(self.episode[row]), list(cams.values()))
            for key, cam in cams.items():
                out[key].append(torch.from_numpy(decoded[cam][self.frame[row]]))
        return {key: torch.stack(v).permute(0, 3, 1, 2).float().div_(255) for key, v in out.items()}

    def rows(self, batch: int) -> np.ndarray:
        return self.rng.integers(0, len(self.episode), batch)


def measure(fn: Callable[[], object], repeats: int, memory: Memory) -> dict:
    """Median seconds of `fn` (one warm-up), with the phase's memory peaks."""
    def synced() -> None:
        fn()
        if memory.device.type == "cuda":
            torch.cuda.synchronize(memory.device)

    memory.reset()
    seconds = median_seconds(synced, repeats)
    return {"seconds": seconds, **memory.peaks()}


def flow_step(adapter, make_raw: Callable[[np.ndarray], dict], frames: Frames, batch: int, dtype: torch.dtype,
              g: torch.Generator) -> Callable[[], None]:
    """One optimiser step over the trainable parameters on a batch from `make_raw(rows)` (flow time from
    the policy's own sampler)."""
    opt = torch.optim.AdamW([p for p in adapter.policy.parameters() if p.requires_grad], lr=1e-4)

    def step() -> None:
        prepared = adapter.prepare(make_raw(frames.rows(batch)))
        with autocast(adapter.device, dtype):
            loss = adapter.loss(prepared, noise=adapter.sample_noise(batch, generator=g)).mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
    return step


def predict(adapter, make_raw: Callable[[np.ndarray], dict], frames: Frames, batch: int, dtype: torch.dtype,
            g: torch.Generator) -> Callable[[], None]:
    def run() -> None:
        raw = make_raw(frames.rows(batch))
        del raw["action"], raw["action_is_pad"]
        with torch.no_grad(), autocast(adapter.device, dtype):
            adapter.predict(adapter.prepare(raw), noise=adapter.sample_noise(batch, generator=g))
    return run


def built(name: str, a: argparse.Namespace, dtype_name: str, log: Callable[[dict], None]) -> tuple[str, Path]:
    """The random-init released-geometry checkpoint of `name` in `--hub` (built unless this environment built
    it already): its hub id and snapshot folder. pi0.5 is written in the compute dtype (bf16: LM and expert
    bf16, vision path and norms fp32), SmolVLA in fp32 as released."""
    options = {"dtype": {"bf16": "bfloat16", "fp32": "float32"}[dtype_name]} if name == "pi05" else {}
    repo = f"graftcache-bench/{name}-libero-random" + (f"-{dtype_name}" if options else "")
    ref = a.hub / f"models--{repo.replace('/', '--')}" / "refs" / "main"
    t0 = time.perf_counter()
    if not (ref.is_file() and built_here(ref.parents[1] / "snapshots" / ref.read_text())):
        BUILDERS[name](repo, cache=a.hub, **options)
    log({"backbone": name, "batch": None, "phase": "build", "seconds": time.perf_counter() - t0})
    return repo, ref.parents[1] / "snapshots" / ref.read_text()


def current_rss_gb() -> float:
    """Resident memory now (VmRSS)."""
    line = next(ln for ln in Path("/proc/self/status").read_text().splitlines() if ln.startswith("VmRSS:"))
    return int(line.split()[1]) * 1024 / 1e9


def import_policy_code(name: str) -> None:
    """Import lerobot's policy module and what it pulls in (transformers, custom kernels: tens of seconds on a
    busy machine), so `load` times the load alone."""
    from lerobot.policies.factory import get_policy_class

    get_backbone(name)
    get_policy_class(name)


def bench_load(name: str, a: argparse.Namespace, device: torch.device, dtype_name: str, memory: Memory,
               log: Callable[[dict], None]) -> None:
    """`--only load`: the load's seconds and peak RSS against the checkpoint's bytes (target: peak <= 1.25 x
    checkpoint + 2 GB on a CPU), then what a graft and a reset add to the resident memory (target: nothing)."""
    repo, snapshot = built(name, a, dtype_name, log)
    checkpoint = (snapshot / "model.safetensors").stat().st_size
    t0 = time.perf_counter()
    import_policy_code(name)
    log({"backbone": name, "batch": None, "phase": "import", "seconds": time.perf_counter() - t0})
    before = current_rss_gb()
    memory.reset()
    t0 = time.perf_counter()
    adapter = load_backbone(name, repo, device=str(device))
    seconds = time.perf_counter() - t0
    peaks = memory.peaks()
    target = 1.25 * checkpoint / 1e9 + 2
    log({"backbone": name, "batch": None, "phase": "load", "seconds": seconds, **peaks,
         "rss_before_gb": before, "rss_after_gb": current_rss_gb(), "checkpoint_gb": checkpoint / 1e9,
         "peak_rss_over_checkpoint": peaks["peak_rss_gb"] * 1e9 / checkpoint,
         "cpu_target_gb": target, "meets_cpu_target": peaks["peak_rss_gb"] <= target,
         "dtypes": sorted({str(p.dtype).removeprefix("torch.") for p in adapter.policy.parameters()})})
    loaded = current_rss_gb()
    memory.reset()
    t0 = time.perf_counter()
    _ = adapter.policy_sha256  # what graft() computes first (pinned identity of the loaded weights)
    tower, _ = adapter._tower_and_connector()
    adapter.graft(GraftProjector(tower.config.hidden_size, adapter.lm_width))  # the native tower's width
    log({"backbone": name, "batch": None, "phase": "graft", "seconds": time.perf_counter() - t0, **memory.peaks(),
         "rss_growth_gb": current_rss_gb() - loaded})
    memory.reset()
    t0 = time.perf_counter()
    adapter.reset()
    log({"backbone": name, "batch": None, "phase": "reset", "seconds": time.perf_counter() - t0, **memory.peaks(),
         "rss_growth_gb": current_rss_gb() - loaded})


def bench_backbone(name: str, a: argparse.Namespace, device: torch.device, dtype_name: str, frames: Frames,
                   memory: Memory, log: Callable[[dict], None]) -> None:
    dtype = resolve_dtype(dtype_name)
    repo, _ = built(name, a, dtype_name, log)
    memory.reset()
    t0 = time.perf_counter()
    adapter = load_backbone(name, repo, device=str(device))
    log({"backbone": name, "batch": None, "phase": "load", "seconds": time.perf_counter() - t0,
         **memory.peaks()})
    cams = {key: key.removeprefix("observation.images.") for key in adapter.camera_keys}  # LIBERO's names
    width = adapter.native_patch_grid(torch.zeros(1, 3, 256, 256)).shape[-1]
    g = torch.Generator().manual_seed(0)

    def online(rows: np.ndarray) -> dict:
        return {**frames.pixels(rows, cams), **frames.lowdim(rows)}

    _, connector = adapter._tower_and_connector()
    freeze_all_but(adapter.policy, connector)  # trains the connector, as a graft trains the projector
    adapter.policy.train()
    for b in a.batches:
        log({"backbone": name, "batch": b, "phase": "online step",
             **measure(flow_step(adapter, online, frames, b, dtype, g), a.repeats, memory)})
        log({"backbone": name, "batch": b, "phase": "online predict",
             **measure(predict(adapter, online, frames, b, dtype, g), a.repeats, memory)})

    memory.reset()
    t0 = time.perf_counter()
    adapter.graft(GraftProjector(width, adapter.lm_width))
    log({"backbone": name, "batch": None, "phase": "graft", "seconds": time.perf_counter() - t0,
         **memory.peaks()})
    tokens = adapter.token_grid[0] * adapter.token_grid[1]
    rows_memory = torch.randn(64, tokens, width, generator=g).half()  # a cache's rows, in memory

    def cached(rows: np.ndarray) -> dict:
        picks = torch.from_numpy(rows % len(rows_memory))
        return {**{feature_key(key): rows_memory[picks].float() for key in cams}, **frames.lowdim(rows)}

    adapter.policy.train()
    for b in a.batches:
        log({"backbone": name, "batch": b, "phase": "cached step",
             **measure(flow_step(adapter, cached, frames, b, dtype, g), a.repeats, memory)})
        log({"backbone": name, "batch": b, "phase": "cached predict",
             **measure(predict(adapter, cached, frames, b, dtype, g), a.repeats, memory)})
    del adapter
    rows_memory = None  # frees the rows (`cached`, done with, reads the same variable)
    gc.collect()  # the graft's instance override makes policy and adapter a cycle
    if device.type == "cuda":
        torch.cuda.empty_cache()


def table(rows: list[dict]) -> str:
    """Compact table: one line per phase, then the cached / online ratios."""
    def gb(v: float | None) -> str:
        return "-" if v is None else f"{v:.1f}"

    lines = [f"{'backbone':8} {'batch':>5} {'phase':15} {'seconds':>9} {'peak RSS GB':>11} "
             f"{'peak CUDA GB':>12}"]
    for r in rows:
        lines.append(f"{r['backbone']:8} {r['batch'] or '':>5} {r['phase']:15} {r['seconds']:9.3f} "
                     f"{gb(r.get('peak_rss_gb')):>11} {gb(r.get('peak_cuda_gb')):>12}")
    by = {(r["backbone"], r["batch"], r["phase"]): r["seconds"] for r in rows}
    for (name, b, phase), seconds in by.items():
        if phase.startswith("cached"):
            what = phase.split()[1]
            online = by[(name, b, f"online {what}")]
            lines.append(f"{name:8} {b:>5} cached/online {what}: {seconds / online:.3f} "
                         f"(online {online / seconds:.1f}x)")
    return "\n".join(lines)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--device", default="cpu", help="cpu, cuda or cuda:N")
    p.add_argument("--compute-dtype", default="auto", choices=("auto", "bf16", "fp32"))
    p.add_argument("--backbones", "--backbone", default="smolvla,pi05")
    p.add_argument("--only", choices=("load",),
                   help="load: only load, graft and reset each backbone (seconds, peak RSS against the checkpoint's "
                        "bytes); needs no dataset, and runs pi0.5 on a CPU without --cpu-pi05 (~10 GB)")
    p.add_argument("--batches", default="1,4")
    p.add_argument("--repeats", type=int, default=5, help="timed calls per phase, after one warm-up")
    p.add_argument("--dataset", type=Path, default=DEFAULT_DATASET)
    p.add_argument("--hub", type=Path, default=DEFAULT_HUB,
                   help="HF hub cache for the built checkpoints (11 GB; reused when built with the same "
                        "lerobot, transformers and torch)")
    p.add_argument("--threads", type=int, default=None, help="torch intra-op threads (default: all cores)")
    p.add_argument("--cpu-pi05", action="store_true",
                   help="run pi0.5 on a CPU (~30 GB of RAM, ~10 min per step)")
    p.add_argument("--out", type=Path, help="also write the results as JSON here (after every row)")
    a = p.parse_args()
    a.batches = [int(b) for b in a.batches.split(",")]
    names = [n for n in a.backbones.split(",") if n]
    unknown = sorted(set(names) - set(BUILDERS))
    if unknown:
        p.error(f"unknown backbone(s) {', '.join(unknown)}; choose from {', '.join(BUILDERS)}")

    device = resolve_device(a.device)
    dtype_name = resolve_compute_dtype(a.compute_dtype, device)
    set_main_threads(a.threads)
    if device.type == "cpu" and "pi05" in names and not a.cpu_pi05 and a.only != "load":
        print("skipping pi05 on cpu (pass --cpu-pi05 to run it)")
        names.remove("pi05")
    if a.only is None:
        warm_page_cache(a.dataset)
    gpu = f"; {torch.cuda.get_device_name(device)}" if device.type == "cuda" else ""
    bf16 = "yes" if "avx512_bf16" in Path("/proc/cpuinfo").read_text() else "no"
    header = f"machine: {machine()}, avx512_bf16 {bf16}{gpu}; device {device}, compute {dtype_name}"
    print(header, flush=True)
    rows: list[dict] = []

    def log(row: dict) -> None:
        """Print a row and rewrite --out, so a run cut short (a time limit, an error) keeps its rows."""
        rows.append(row)
        print(json.dumps(row), flush=True)
        if a.out:
            a.out.write_text(json.dumps({"machine": header, "device": str(device),
                                         "compute_dtype": dtype_name, "repeats": a.repeats, "results": rows},
                                        indent=1))

    memory = Memory(device)
    with hub_cache(a.hub):
        if a.only == "load":
            for name in names:
                bench_load(name, a, device, dtype_name, memory, log)
            return
        frames = Frames(a.dataset, chunk=LIBERO.chunk_size)
        for name in names:
            bench_backbone(name, a, device, dtype_name, frames, memory, log)
    print(table(rows))


if __name__ == "__main__":
    main()
