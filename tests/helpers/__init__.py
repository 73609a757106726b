"""Plain helpers shared by tests (writers, tiny models, hand-built tables), imported normally;
fixtures live in tests/fixtures and tests/conftest.py.

One of each: requests.py builds every test's ExtractRequest and FitRequest, world.py is the stage-2 world (dataset,
tiny checkpoints, caches) a module builds once, caches.py's `write_cache` writes every synthetic cache (benchmarks
too), previous_formats.py every cache and results file of an older format."""
