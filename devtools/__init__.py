"""Developer tools beside the graftcache library: what tests and benchmarks build, never what a user's run reads.

released.py   random-init SmolVLA / pi0.5 checkpoints at the released geometry, in the hub-cache layout
              (`BUILDERS`, `built_here`: reuse a build made under this environment's library versions)
tile/         `python -m devtools.tile`: bigger v3.0 datasets whose episodes are windows of a small one's frames

graftcache never imports devtools (tests/test_imports.py); devtools imports graftcache.
"""
