"""The ray executor's extraction: one cache's blocks split into shards, each extracted by one Ray task.

Task i of N runs the ordinary extraction with `shard=(i, N)` (graftcache.extract.extract): it fills only its
shard's blocks, skips blocks already written (so a task Ray reruns after its worker died redoes only the
blocks that worker had not finished), and the last shard to finish publishes the cache `complete`. The
driver fixes what every task must agree on before any runs: the cache root, local paths, and the compute
dtype as the workers resolve it (it is part of the cache key).

How many shards by default (`shards` unset): as many as the cluster runs at once for the task's resources,
its GPUs over `gpus_per_task` (CPUs over `cpus_per_task` on CPU). Every slot then encodes, and each task
loads the encoder and opens the dataset once; more shards than slots would only add those loads, fewer would
leave GPUs idle. On a CPU-only machine with `ray.init(num_cpus=2)` that is 2.
"""

from __future__ import annotations

import dataclasses
import time

import ray

from graftcache.errors import CacheError
from graftcache.executors import Log
from graftcache.executors.ray_cluster import (
    connect,
    finished,
    local_path,
    shared_root,
    slots,
    task_options,
    worker_compute_dtype,
)
from graftcache.extract import ExtractResult, extract
from graftcache.requests import ExecutorSettings, ExtractRequest


def extract_shard(req: ExtractRequest) -> ExtractResult:
    """One shard's blocks (`req.shard`), extracted in a Ray worker (run as `extract_shard_task`)."""
    return extract(req)


#: The Ray task of `extract_shard`, kept apart so that cloudpickle ships the function by reference (see ray_fit).
extract_shard_task = ray.remote(extract_shard)


def shared_request(req: ExtractRequest, compute_dtype: str) -> ExtractRequest:
    """`req` as every shard must read it: local paths absolute, the cache root fixed, the dtype resolved."""
    return dataclasses.replace(req, dataset=local_path(req.dataset), weights=local_path(req.weights),
                               policy=local_path(req.policy), cache=shared_root(req.cache),
                               compute_dtype=compute_dtype, progress=False)


def extract_cache(req: ExtractRequest, settings: ExecutorSettings, log: Log) -> ExtractResult:
    """The complete cache of `req`, its blocks extracted by `settings.shards` Ray tasks."""
    t0 = time.perf_counter()
    connect(settings, log)
    options = task_options(settings, req.device)
    n = settings.shards or slots(options)
    req = shared_request(req, worker_compute_dtype(req.compute_dtype, req.device, options))
    log(f"ray: extract {req.encoder} as {n} shard task(s), {options['num_gpus']:g} GPU and {options['num_cpus']:g} "
        f"CPU each")
    tasks = {extract_shard_task.options(**options).remote(dataclasses.replace(req, shard=(i, n))): f"shard {i}/{n}"
             for i in range(n)}
    shards = [result for _, result in finished(tasks)]
    if not any(s.complete for s in shards):
        raise CacheError(f"cache {shards[0].key}: every shard finished but none published it complete")
    first = shards[0]
    encoded = sum(s.frames_encoded for s in shards)
    wall = time.perf_counter() - t0
    log(f"{'reusing' if not encoded else 'wrote'} {first.key}: {first.n_frames} frames, {encoded} encoded by "
        f"{n} shard(s) in {wall:.1f}s -> {first.path}")
    return ExtractResult(first.key, first.path, all(s.reused for s in shards), first.n_frames, encoded, wall,
                         max(s.encode_s for s in shards), complete=True)
