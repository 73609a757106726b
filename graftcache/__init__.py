"""graftcache: test vision encoders on frozen VLA backbones from cached features.

Stage 1 (`graftcache extract`) turns every frame of a LeRobot LIBERO dataset into pooled encoder
features stored in Zarr with a provenance manifest. Stage 2 (`graftcache fit`) trains only a
LayerNorm + Linear projector into a frozen lerobot VLA backbone from that cache and scores offline
action MSE. See docs/ARCHITECTURE.md for the data flow.
"""

__version__ = "0.1.0"
