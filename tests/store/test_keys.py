"""Keys are names, not paths (issue 24, item 1): every command that takes a key checks it against the key
grammar before any I/O, nothing outside the cache root is read, written or deleted, symbolic links in a root
are refused and never followed, a folder holding a cache whose manifest hashes to another key is not that
cache, and a `--cache` that is a regular file is refused by name. Each case runs the CLI in-process and checks
the exit code, that stderr is one line naming the key or path (no traceback), and that no file anywhere in the
test's folder changed (a sentinel beside the root included)."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest
from fixtures.s3 import bucket_objects
from helpers.caches import synthetic_cache
from helpers.datasets import Written

from graftcache.cli import main
from graftcache.errors import CacheError
from graftcache.store import FeatureCache, cache_key
from graftcache.store.cache import ArraySpec

#: A key in the grammar that no cache of these tests hashes to (what a hand-renamed folder is called).
FOREIGN = f"synthetic-{'f' * 16}"
SENTINEL = "docs/thesis.txt"
FIT = ["fit", "--backbone", "smolvla", "--encoder", "synthetic", "--suite", "libero_spatial", "--steps", "1",
       "--no-progress"]


@pytest.fixture(scope="module")
def made(tmp_path_factory: pytest.TempPathFactory) -> FeatureCache:
    """A small complete cache (11 frames, 3 blocks), copied into each test's folder."""
    return synthetic_cache(tmp_path_factory.mktemp("made"), [6, 5], grid=(2, 2), width=4, block_frames=4)


def _tree(folder: Path) -> dict[str, bytes | str]:
    """Every file's bytes and every link's target under `folder`, never following a link."""
    out: dict[str, bytes | str] = {}
    for at, dirs, files in os.walk(folder):
        for name in dirs + files:
            path = Path(at, name)
            rel = path.relative_to(folder).as_posix()
            if path.is_symlink():
                out[rel] = f"-> {os.readlink(path)}"
            elif path.is_file():
                out[rel] = path.read_bytes()
    return out


def _sentinel(folder: Path) -> Path:
    (folder / SENTINEL).parent.mkdir(parents=True, exist_ok=True)
    (folder / SENTINEL).write_text("four years of work")
    return folder


def _refused(argv: list[str], capsys: pytest.CaptureFixture, *named: object) -> str:
    """Run the CLI: exit 2 with one line on stderr naming every one of `named`, no traceback."""
    assert main([str(a) for a in argv]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    for name in named:
        assert str(name) in err, (name, err)
    return err


#: {src}: a root holding the cache; {root}: the user's root, beside a folder of theirs holding a sentinel;
#: {other}: a complete cache outside every root, at src/../victim.
PATH_KEYS = {
    "pull ../victim": ["pull", "../victim", "{src}", "--cache", "{root}"],
    "push ../victim": ["push", "../victim", "{root}", "--cache", "{src}"],
    "info ../victim": ["info", "../victim", "--cache", "{src}"],
    "verify ../victim": ["verify", "../victim", "--cache", "{src}"],
    "pull absolute": ["pull", "{other}", "{src}", "--cache", "{root}"],
    "info absolute": ["info", "{other}", "--cache", "{root}"],
    "verify absolute": ["verify", "{other}", "--cache", "{root}"],
    "fit --cache-key ../../": [*FIT, "--cache-key", "../../there/victim", "--cache", "{root}"],
    "fit --cache-key absolute": [*FIT, "--cache-key", "{other}", "--cache", "{root}"],
}


@pytest.mark.parametrize("argv", PATH_KEYS.values(), ids=PATH_KEYS.keys())
def test_a_path_is_not_a_key(argv: list[str], made: FeatureCache, tmp_path: Path,
                             capsys: pytest.CaptureFixture) -> None:
    src, root, other = tmp_path / "there" / "src", tmp_path / "here" / "root", tmp_path / "there" / "victim"
    victim = tmp_path / "here" / "victim"  # ROOT/../victim
    shutil.copytree(made.path, src / made.key)
    shutil.copytree(made.path, other)
    root.mkdir(parents=True)
    _sentinel(victim)
    before = _tree(tmp_path)
    argv = [a.format(src=src, root=root, other=other) for a in argv]
    key = argv[argv.index("--cache-key") + 1] if "--cache-key" in argv else argv[1]
    _refused([*argv, "--results", tmp_path / "r.parquet"] if argv[0] == "fit" else argv, capsys,
             repr(key), "is not a cache key")
    assert _tree(tmp_path) == before


def test_a_symlinked_key_folder_is_refused_not_followed(made: FeatureCache, tmp_path: Path,
                                                       capsys: pytest.CaptureFixture) -> None:
    src, root, elsewhere = tmp_path / "src", tmp_path / "root", _sentinel(tmp_path / "elsewhere")
    shutil.copytree(made.path, src / made.key)
    shutil.copytree(made.path, tmp_path / "copy")
    root.mkdir()
    (root / made.key).symlink_to(elsewhere, target_is_directory=True)  # pull would copy into it
    (src / FOREIGN).symlink_to(tmp_path / "copy", target_is_directory=True)  # a cache outside the root
    before = _tree(tmp_path)
    _refused(["pull", made.key, src, "--cache", root], capsys, root / made.key, "symbolic link")
    _refused(["push", made.key, root, "--cache", src], capsys, root / made.key, "symbolic link")
    for command in ("info", "verify"):
        _refused([command, FOREIGN, "--cache", src], capsys, src / FOREIGN, "symbolic link")
    assert _tree(tmp_path) == before


def test_a_file_under_a_key_s_name_is_refused(made: FeatureCache, tmp_path: Path,
                                              capsys: pytest.CaptureFixture) -> None:
    src, root = tmp_path / "src", tmp_path / "root"
    shutil.copytree(made.path, src / made.key)
    root.mkdir()
    (root / made.key).write_text("a user's file named like a key")
    before = _tree(tmp_path)
    _refused(["pull", made.key, src, "--cache", root], capsys, root / made.key, "is a file")
    _refused(["info", made.key, "--cache", root], capsys, root / made.key, "is a file")
    assert _tree(tmp_path) == before


def test_a_link_inside_a_cache_is_never_followed(made: FeatureCache, tmp_path: Path,
                                                capsys: pytest.CaptureFixture) -> None:
    """The destination's copy lacks lowdim/state (a link to a folder of the user's): pull would drop the
    'damaged' array's folder and copy it again, through the link."""
    src, root, elsewhere = tmp_path / "src", tmp_path / "root", _sentinel(tmp_path / "elsewhere")
    shutil.copytree(made.path, src / made.key)
    shutil.copytree(made.path, root / made.key)
    shutil.rmtree(root / made.key / "lowdim" / "state")
    (root / made.key / "lowdim" / "state").symlink_to(elsewhere, target_is_directory=True)
    before = _tree(tmp_path)
    link = root / made.key / "lowdim" / "state"
    _refused(["pull", made.key, src, "--cache", root], capsys, link, "symbolic link")
    _refused(["verify", made.key, "--cache", root], capsys, link, "symbolic link")
    assert _tree(tmp_path) == before


def test_a_renamed_cache_folder_is_not_that_cache(made: FeatureCache, tmp_path: Path,
                                                 capsys: pytest.CaptureFixture) -> None:
    root, dest = tmp_path / "root", tmp_path / "dest"
    shutil.copytree(made.path, root / FOREIGN)  # copied by hand under a key that is not its own
    before = _tree(tmp_path)
    for command in ("verify", "info"):
        _refused([command, FOREIGN, "--cache", root], capsys, f"not cache {FOREIGN}", f"hashes to {made.key}")
    _refused(["pull", FOREIGN, root, "--cache", dest], capsys, FOREIGN, made.key)
    _refused([*FIT, "--cache", root, "--cache-key", FOREIGN, "--results", tmp_path / "r.parquet"], capsys,
             FOREIGN, made.key)
    # without --cache-key the fit does not take it either: it is a broken entry, not a cache of 'synthetic'
    _refused([*FIT, "--cache", root, "--results", tmp_path / "r.parquet"], capsys,
             "no complete cache of encoder")
    assert main(["ls", "--cache", str(root)]) == 0
    row = next(line for line in capsys.readouterr().out.splitlines() if FOREIGN in line)
    assert "BROKEN" in row
    assert _tree(tmp_path) == before


def test_a_cache_is_only_made_under_its_own_key(made: FeatureCache, tmp_path: Path) -> None:
    manifest = made.manifest
    own = cache_key(manifest.to_dict())
    with pytest.raises(CacheError, match=f"made under its own key, {own}, not under '{FOREIGN}'"):
        FeatureCache.create(tmp_path / FOREIGN, manifest, [ArraySpec("features/image/2x2", (4, 4))],
                            made.index(), block_frames=4)
    assert not (tmp_path / FOREIGN).exists()


def test_extract_never_deletes_a_complete_cache_it_did_not_make(
        v3_image: Written, made: FeatureCache, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    root = tmp_path / "root"
    argv = ["extract", "--encoder", "resnet18", "--random-init", "--dataset", str(v3_image.root), "--grids",
            "2x2", "--block-frames", "8", "--num-workers", "0", "--no-progress", "--cache", str(root)]
    assert main(argv) == 0
    key = capsys.readouterr().out.strip().splitlines()[-1]
    shutil.rmtree(root / key)
    shutil.copytree(made.path, root / key)  # another complete cache, stored under this extraction's key
    before = _tree(tmp_path)
    _refused(argv, capsys, f"not cache {key}", f"hashes to {made.key}")
    assert _tree(tmp_path) == before


CACHE_IS_A_FILE = {
    "ls": ["ls", "--cache", "{file}"],
    "info": ["info", FOREIGN, "--cache", "{file}"],
    "verify": ["verify", FOREIGN, "--cache", "{file}"],
    "extract": ["extract", "--encoder", "resnet18", "--dataset", "{tmp}/no-dataset", "--cache", "{file}"],
    "pull into": ["pull", FOREIGN, "{tmp}", "--cache", "{file}"],
    "pull from": ["pull", FOREIGN, "{file}", "--cache", "{tmp}/root"],
    "push": ["push", FOREIGN, "{tmp}/dest", "--cache", "{file}"],
    "fit": [*FIT, "--cache", "{file}", "--results", "{tmp}/r.parquet"],
    "train-tiny": ["train-tiny", "--backbone", "smolvla", "--dataset", "{tmp}/none", "--cache", "{file}"],
}


@pytest.mark.parametrize("argv", CACHE_IS_A_FILE.values(), ids=CACHE_IS_A_FILE.keys())
def test_a_cache_root_that_is_a_file_is_refused_by_name(argv: list[str], tmp_path: Path,
                                                        capsys: pytest.CaptureFixture) -> None:
    file = tmp_path / "notes.txt"
    file.write_text("not a folder")
    before = _tree(tmp_path)
    _refused([a.format(file=file, tmp=tmp_path) for a in argv], capsys, f"cache root {file} is a file")
    assert _tree(tmp_path) == before


def test_object_store_roots_take_names_only(s3: str, made: FeatureCache, tmp_path: Path,
                                            capsys: pytest.CaptureFixture) -> None:
    """A path handed to push as a key used to leave a lease and a pending zarr.json in the bucket."""
    root = tmp_path / "root"
    shutil.copytree(made.path, root / made.key)
    before = _tree(tmp_path)
    _refused(["push", root / made.key, s3, "--cache", root], capsys, repr(str(root / made.key)))
    _refused(["pull", "../victim", s3, "--cache", root], capsys, repr("../victim"))
    _refused(["info", f"x/../{made.key}", "--cache", s3], capsys, repr(f"x/../{made.key}"))
    assert bucket_objects(s3) == {}
    assert _tree(tmp_path) == before
