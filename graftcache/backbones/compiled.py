"""torch.compile of a backbone's frozen training forward (`fit --compile`), installed and undone through
graftcache.backbones.patching like every other change to a lerobot object.

What is compiled is the one module whose forward the training loss calls (the spec's `compiled_forward`, e.g. pi0.5's
`policy.model`: its prefix, LM, expert and flow head), with the graft's projector inside it (traced with the rest, so
its gradients flow as eagerly). Compiling costs seconds to minutes once per training pass (and again where a batch's
shape changes), so it pays only over enough steps: benchmarks/gpu_check.py measures the compile seconds against the
seconds it saves a step. Scoring (the denoising loop, `predict`) stays eager. The numbers agree with the eager
forward's within float rounding (tests/backbones/test_compiled.py), so the setting is in no run_id.
"""

from __future__ import annotations

from operator import attrgetter

import torch

from graftcache.backbones.patching import Patches
from graftcache.errors import BackboneError


def compile_forward(adapter, backend: str = "inductor") -> Patches:
    """The adapter's training forward replaced by its torch.compile'd self (`backend`: torch's compiler backend,
    inductor by default); undo the returned Patches to run eagerly again. A backbone whose spec names no such forward
    is refused in one line."""
    path = adapter.spec.compiled_forward
    if path is None:
        raise BackboneError(f"{adapter.name}: no compiled forward for this backbone (its spec names none); drop "
                            "--compile")
    module = attrgetter(path)(adapter)
    patches = Patches()
    patches.set(module, "forward", torch.compile(module.forward, backend=backend))
    return patches
