"""Stage 1: decode every frame once, encode, and persist fp16 features with provenance: the encoder's own
patch grid (`--grids unpooled`, the default) and any pooled grids asked for.

Data flow (forward only): worker processes decode whole episodes (frames.py) -> the main process fills a block
buffer of `block_frames` frames and encodes it in batches (blocks.py, encode.py) -> a writer thread writes it
while the next block is encoded, under the write protocol (write.py). Blocks already marked done in the cache
are never decoded again, so a rerun after Ctrl-C or SIGKILL continues from what is durably written, and batch
composition (aligned to blocks) is the same as in an uninterrupted run, which makes the final bytes identical.

One job per module: resolve.py (the request resolved into a job.py Job: dataset, encoder, frames), provenance.py
(index, manifest), frames.py (decode), encode.py (encoder -> stored grids), blocks.py (assembling, encoding and
writing blocks), write.py (reuse / resume / create, whole or as one shard of N, under the writer locks), refusals.py
(refusals before work and the one-line texts of failures during it).
"""

from __future__ import annotations

import time
from collections.abc import Callable

from graftcache.encoders.fingerprint import fingerprint
from graftcache.extract.blocks import fill
from graftcache.extract.encode import encode_frames
from graftcache.extract.job import Job, Target
from graftcache.extract.provenance import build_index, build_manifest, weights_note
from graftcache.extract.refusals import check_disk, check_memory
from graftcache.extract.resolve import resolve_job
from graftcache.extract.write import ExtractResult, Writing, check_numerics, find_complete, shard_blocks
from graftcache.requests import ExtractRequest
from graftcache.runtime import set_main_threads
from graftcache.store import FeatureCache, cache_key, open_root

__all__ = ["ExtractRequest", "ExtractResult", "Job", "build_index", "check_memory", "encode_frames", "extract",
           "fill", "shard_blocks"]


def extract(req: ExtractRequest, log: Callable[[str], None] = print) -> ExtractResult:
    """Run stage 1 for one (dataset, encoder) request; reuse or resume the cache when it exists."""
    t0 = time.perf_counter()
    root = open_root(req.cache)  # a --cache that cannot be a root is refused before any work
    set_main_threads()
    job = resolve_job(req, log)  # the dataset, the encoder and the frames; refused here when they cannot be done
    manifest = build_manifest(job, fingerprint(job.encoder, job.req.compute_dtype, job.device))
    target = Target(root, cache_key(manifest.to_dict()), manifest)
    note = weights_note(manifest)
    if note:
        log(note)

    done = find_complete(target, job)  # reusing takes no writer lock: a read-only root serves it
    if done is not None:
        check_numerics(done, manifest, log)
    else:
        check_disk(target, job)
        writing = Writing(target, job, log, t0)
        result = writing.whole() if req.shard is None else writing.shard(*req.shard)
        if result is not None:
            return result
        done = FeatureCache.in_root(root, target.key)
    log(f"reusing complete cache {target.key} ({done.n_frames} frames)")
    return ExtractResult(target.key, root.location(target.key), True, done.n_frames, 0, time.perf_counter() - t0)
