"""A fitted cell as a lerobot policy (`graftcache export`): what `lerobot-eval` and `graftcache rollout` run.

An export folder (bundle.py writes it) holds no copy of a backbone: its config.json (`"type": "graftcache"`,
configuration_graftcache.py) names the base policy, the cell (run_id, control, camera mapping, pool grid, LoRA rank)
and the cache; manifest.json is the cache's manifest (how to rebuild its encoder, and its numerics fingerprint);
projector.safetensors the cell's trained parameters; the base policy's own processors are saved beside them.
modeling_graftcache.py rebuilds the cell from those: lerobot finds it through the plugin distribution
`lerobot_policy_graftcache` (plugins/), which imports the configuration module.
"""
