"""graftcache: test vision encoders on frozen VLA backbones from cached features.

Stage 1 (`graftcache extract`) turns every frame of a LeRobot LIBERO dataset into pooled encoder
features stored in Zarr with a provenance manifest. Stage 2 (`graftcache fit`) trains only a
LayerNorm + Linear projector into a frozen lerobot VLA backbone from that cache and scores offline
action MSE. See docs/ARCHITECTURE.md for the data flow.
"""

import os
import sys

__version__ = "0.1.0"

#: MKL's conditional numerical reproducibility mode for this process: STRICT makes its fp32 matrix products (torch's
#: on x86) sum in an order that does not depend on the thread count, so a run's scores do not either. MKL reads
#: $MKL_CBWR once, when torch loads it: set here, before graftcache imports torch, unless the user set it or torch
#: was imported first (graftcache.runtime.kernels then records what was in effect).
MKL_CBWR = "AUTO,STRICT"
if "torch" not in sys.modules:
    os.environ.setdefault("MKL_CBWR", MKL_CBWR)
