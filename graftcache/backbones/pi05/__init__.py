"""The pi05 backbone (graftcache/backbone_table.py): adapter.py, its adapter; tiny.py, its tiny configuration."""
