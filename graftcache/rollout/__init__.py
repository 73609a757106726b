"""Closed-loop checks (`graftcache rollout`): fitted cells exported (graftcache.export) and run in the LIBERO
simulator through lerobot's own evaluation code, one Parquet row per episode.

A request's way, one module after the other: request.py (what was asked, refused in one line past its bounds),
select.py (which rows: the report's top encoders plus controls, or exact run_ids; what the simulator can feed; the
request with its rows, a Selection), roll_out.py (the selection's episodes, what the rollouts file holds skipped, the
rest handed to a team), schedule.py (the one loop every team's episodes go through: claims, the file reread once per
claim, each cell's summary), teams.py (the Team interface and this process's team of one), record.py (a finished
episode's video and row written), rollouts_file.py (the rollouts file's schema, episode ids and reading).
Beside it: episodes.py (the request's episodes, outcomes, the Simulator interface), libero.py (the simulator:
lerobot's LIBERO env and rollout loop, in this process), simulator_setup.py (a process's set-up around the
simulator: its libraries checked, their chatter quieted, the policy's threads), render_callback.py (what lerobot's
rollout calls after the reset and every step: the state read, the frame kept), graded.py (graded progress from the
simulator's state), perturb.py (the target's seeded perturbation, --perturb-cm), seam.py (every reach past lerobot's,
hf-libero's and robosuite's public API, and the versions it was read in), workers.py (`--workers N`: episodes in N
spawned processes, each with its own simulator), worker_process.py (a worker's loop, in the spawned process),
sequential.py (`--until-resolved`: looks that add episodes to the pairs still unresolved).
"""
