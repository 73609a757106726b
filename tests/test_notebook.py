"""notebooks/analysis.ipynb runs top to bottom on a hand-built results file and draws its figures."""

from __future__ import annotations

from helpers.notebook import NOTEBOOK, execute_notebook, nbformat
from helpers.tables import write_results


def test_notebook_is_stored_without_outputs():
    nb = nbformat.read(NOTEBOOK, as_version=4)
    nbformat.validate(nb)
    code = [c for c in nb.cells if c.cell_type == "code"]
    assert code and all(not c.outputs and c.execution_count is None for c in code)
    assert "GRAFTCACHE_RESULTS" in code[0].source  # the parameter cell comes first


def test_notebook_executes_and_draws_figures(tmp_path, monkeypatch):
    run = execute_notebook(write_results(tmp_path / "results.parquet"), tmp_path, monkeypatch)
    assert not run.errors
    assert "On libero_spatial, the SmolVLA winner (siglip) is in pi0.5's top tier: the ranking transfers." in run.text
    assert "SmolVLA · libero_spatial: separated on every seed" in run.text  # the controls' findings
    assert "SmolVLA: siglip on libero_spatial (real weights) beats both image controls on every seed" in run.text
    assert run.figures == 3  # rank transfer, MSE, controls
