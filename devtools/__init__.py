"""Developer tools beside the graftcache library: what tests and benchmarks build, never what a user's run reads.

released.py   random-init SmolVLA / pi0.5 checkpoints at the released geometry, in the hub-cache layout
              (`BUILDERS`, `built_here`: reuse a build made under this environment's library versions)
tile/         `python -m devtools.tile`: bigger v3.0 datasets whose episodes are windows of a small one's frames
suite_durations.py
              `python -m devtools.suite_durations`: tests/durations.json (seconds per test module, which the
              suite's xdist schedule starts longest first) from a full run's junit XML

graftcache never imports devtools (tests/test_imports.py); devtools imports graftcache.
"""
