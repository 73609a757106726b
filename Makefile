# The two commands a new user needs (see README): `make demo` and `make test` (ruff, then pytest: what CI runs).
# Both set up .venv first (scripts/setup.sh is idempotent) and run fully offline.
export HF_HUB_OFFLINE := 1
export HF_DATASETS_OFFLINE := 1
export TRANSFORMERS_OFFLINE := 1

# `make test` also sets up the LIBERO simulator (the closed-loop smoke test); `make demo` does not need it.
.PHONY: setup setup-libero demo demo-closed-loop lint test test-fast bench

setup:
	bash scripts/setup.sh

setup-libero:
	bash scripts/setup.sh libero

demo: setup
	.venv/bin/graftcache demo

# the demo's cells in the LIBERO simulator, for the offline-vs-closed-loop figure (docs/closed-loop.md)
demo-closed-loop: setup-libero
	.venv/bin/graftcache demo --closed-loop

lint: setup
	.venv/bin/ruff check .

# one pytest-xdist worker per core, each test module (the tiny zoo's: each backbone) on one worker, the longest first
# by tests/durations.json (tests/helpers/parallel.py; regenerate it with `python -m devtools.suite_durations`)
test: setup-libero lint
	.venv/bin/python -m pytest -q -n auto --dist loadgroup --durations=30

test-fast: setup
	.venv/bin/python -m pytest -q -m "not slow"

bench: setup
	.venv/bin/python benchmarks/bench_reader.py
	.venv/bin/python benchmarks/bench_extract.py
	.venv/bin/python benchmarks/bench_fit.py
	.venv/bin/python benchmarks/bench_store.py
