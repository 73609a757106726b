"""graftcache.upstream: the releases graftcache's reaches into lerobot, hf-libero and robosuite were read in, checked
before either house reaches (the rollout's seam: tests/rollout/test_seam.py; the backbone adapters: here). Another
installed release is refused in one line naming the reader, both versions and the pin; the backbone registry checks
lerobot before it imports an adapter, so `graftcache train-tiny` says it in one line and exits 2."""

from __future__ import annotations

from pathlib import Path

import pytest
from helpers.probes import run_cli
from helpers.versions import installed_as, not_installed

from graftcache import upstream
from graftcache.backbones import get_backbone, load_backbone, registered_spec
from graftcache.errors import BackboneError, GraftcacheError

SAMPLE = Path(__file__).resolve().parents[1] / "data" / "libero_sample"


def test_the_table_is_this_environments_pins() -> None:
    """The venv set up by the README's commands holds exactly the releases the reaches were read in (lerobot is a core
    dependency; hf-libero and robosuite come with the simulator's set-up)."""
    assert upstream.installed("lerobot") == upstream.WRITTEN_AGAINST["lerobot"]
    assert {n: upstream.installed(n) for n in upstream.WRITTEN_AGAINST} == upstream.WRITTEN_AGAINST
    pyproject = (Path(__file__).resolve().parents[1] / "pyproject.toml").read_text()
    assert pyproject.count(f"]=={upstream.WRITTEN_AGAINST['lerobot']}\"") == 2  # the core pin and the libero extra


def test_another_release_is_refused_naming_the_reader_both_versions_and_the_pin(
        monkeypatch: pytest.MonkeyPatch) -> None:
    upstream.refuse_others(("lerobot", "robosuite"), "reader.py", GraftcacheError)  # the pins: passes
    installed_as(monkeypatch, lerobot="0.7.0", robosuite="1.5.1")
    with pytest.raises(BackboneError) as refused:
        upstream.refuse_others(("lerobot", "hf-libero", "robosuite"), "reader.py", BackboneError)
    assert str(refused.value) == ("reader.py was written against lerobot 0.6.1, robosuite 1.4.0, not the installed "
                                  "lerobot 0.7.0, robosuite 1.5.1: pin lerobot==0.6.1 robosuite==1.4.0")
    upstream.refuse_others(("hf-libero",), "reader.py", BackboneError)  # only the distributions asked about


def test_a_distribution_not_installed_passes(monkeypatch: pytest.MonkeyPatch) -> None:
    not_installed(monkeypatch, "robosuite")
    assert upstream.installed("robosuite") is None
    upstream.refuse_others(("robosuite",), "reader.py", GraftcacheError)


def test_the_backbone_registry_refuses_another_lerobot_before_importing_an_adapter(
        monkeypatch: pytest.MonkeyPatch) -> None:
    assert get_backbone("smolvla").name == "smolvla"  # the pinned release: as always
    installed_as(monkeypatch, lerobot="0.7.0")
    for call in (lambda: get_backbone("xvla"), lambda: load_backbone("evo1", "tiny")):
        with pytest.raises(BackboneError) as refused:
            call()
        assert str(refused.value).endswith("was written against lerobot 0.6.1, not the installed lerobot 0.7.0: "
                                           "pin lerobot==0.6.1")
        assert str(refused.value).startswith(("graftcache/backbones/xvla/ ", "graftcache/backbones/evo1/ "))
    assert registered_spec("smolvla") is not None  # a spec is data: read whatever lerobot is installed


def test_train_tiny_says_it_in_one_line(tmp_path: Path, capsys: pytest.CaptureFixture,
                                        monkeypatch: pytest.MonkeyPatch) -> None:
    installed_as(monkeypatch, lerobot="0.7.0")
    out = run_cli(["train-tiny", "--backbone", "pi0", "--dataset", SAMPLE, "--cache", tmp_path / "cache",
                   "--out", tmp_path / "policy"], capsys)
    assert out.code == 2
    assert out.err.strip().splitlines() == [
        "graftcache train-tiny: error: graftcache/backbones/pi0/ was written against lerobot 0.6.1, not the installed "
        "lerobot 0.7.0: pin lerobot==0.6.1"]
    assert not (tmp_path / "policy" / "model.safetensors").exists()
