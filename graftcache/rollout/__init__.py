"""Closed-loop checks (`graftcache rollout`): fitted cells exported (graftcache.export) and run in the LIBERO
simulator through lerobot's own evaluation code, one Parquet row per episode.

select.py (which rows: the report's top encoders plus controls, or exact run_ids; what the simulator can feed),
episodes.py (planned episodes, outcomes, the Simulator interface), libero.py (the simulator: lerobot's LIBERO env
and rollout loop, in this process), graded.py (graded progress from the simulator's state), perturb.py (the target's
seeded perturbation, --perturb-cm), seam.py (every reach past lerobot's, hf-libero's and robosuite's public API, and
the versions it was read in), workers.py (`--workers N`: episodes in N spawned processes, each with its own
simulator), table.py (the rollouts file's schema and append-safe IO), run.py (plan, skip what the file holds, run
under claims, write each episode).
"""
