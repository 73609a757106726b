"""Comparing two feature caches file by file (a folder, or the objects of a bucket under a key)."""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path

#: Group attributes that record when and how a run happened, not what it computed: two runs of one request
#: (one process or several shards, here or into a bucket) differ in these and nothing else.
RUN_ATTRIBUTES = ("completed_at",)
RUN_MANIFEST_FIELDS = ("created_at", "run")


def folder_files(folder: Path) -> dict[str, bytes]:
    """Every file under a cache folder, by its '/'-separated path inside it."""
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in folder.rglob("*") if p.is_file()}


def assert_same_cache(got: Mapping[str, bytes], want: Mapping[str, bytes]) -> None:
    """The same files with the same bytes, except the group's zarr.json, whose attributes may differ only in
    RUN_ATTRIBUTES and the manifest's RUN_MANIFEST_FIELDS (each present on both sides)."""
    assert set(got) == set(want)
    assert any(rel.startswith("features/") for rel in want)
    for rel in set(want) - {"zarr.json"}:
        assert got[rel] == want[rel], rel
    attrs = [json.loads(files["zarr.json"])["attributes"] for files in (got, want)]
    for a in attrs:
        assert all(a.pop(name) for name in RUN_ATTRIBUTES)
        assert all(a["manifest"].pop(name) for name in RUN_MANIFEST_FIELDS)
    assert attrs[0] == attrs[1]
