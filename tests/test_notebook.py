"""notebooks/analysis.ipynb runs top to bottom on a hand-built results file and draws its figures."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from analysis_fixtures import write_results

nbformat = pytest.importorskip("nbformat")
nbclient = pytest.importorskip("nbclient")

ROOT = Path(__file__).resolve().parents[1]
NOTEBOOK = ROOT / "notebooks" / "analysis.ipynb"


def test_notebook_is_stored_without_outputs():
    nb = nbformat.read(NOTEBOOK, as_version=4)
    nbformat.validate(nb)
    code = [c for c in nb.cells if c.cell_type == "code"]
    assert code and all(not c.outputs and c.execution_count is None for c in code)
    assert "GRAFTCACHE_RESULTS" in code[0].source  # the parameter cell comes first


def test_notebook_executes_and_draws_figures(tmp_path, monkeypatch):
    results = write_results(tmp_path / "results.parquet")
    monkeypatch.setenv("GRAFTCACHE_RESULTS", str(results))
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])))
    monkeypatch.setenv("MPLBACKEND", "agg")
    nb = nbformat.read(NOTEBOOK, as_version=4)
    nb.cells[1].source = nb.cells[1].source.replace(
        "N_BOOT, BOOT_SEED = 0.95, 2000,", "N_BOOT, BOOT_SEED = 0.95, 200,"
    )
    nbclient.NotebookClient(
        nb, timeout=120, kernel_name="python3", resources={"metadata": {"path": str(tmp_path)}}
    ).execute()
    outputs = [o for c in nb.cells if c.cell_type == "code" for o in c.outputs]
    assert not [o for o in outputs if o.output_type == "error"]
    text = "".join(o.get("text", "") for o in outputs if o.output_type == "stream")
    assert (
        "On libero_spatial, the SmolVLA winner (siglip) is in pi0.5's top tier: the ranking transfers."
        in text
    )
    figures = [o for o in outputs if "image/png" in o.get("data", {})]
    assert len(figures) == 3  # rank transfer, MSE, controls
