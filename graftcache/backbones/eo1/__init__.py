"""The eo1 backbone (graftcache/backbone_registry.py): adapter.py, its adapter; tiny.py, its tiny configuration."""
