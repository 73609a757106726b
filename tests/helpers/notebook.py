"""Execute notebooks/analysis.ipynb on a results file, as a user would (nbclient, python3 kernel)."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import pytest

nbformat = pytest.importorskip("nbformat")
nbclient = pytest.importorskip("nbclient")

ROOT = Path(__file__).resolve().parents[2]
NOTEBOOK = ROOT / "notebooks" / "analysis.ipynb"


@dataclass(frozen=True)
class Executed:
    text: str           # everything the cells printed
    errors: list        # error outputs (empty when every cell ran)
    figures: int        # PNG figures drawn


def execute_notebook(results: Path, workdir: Path, monkeypatch: pytest.MonkeyPatch, n_boot: int = 200) -> Executed:
    """Run the notebook top to bottom on `results` (fewer bootstrap draws than the default, for speed)."""
    monkeypatch.setenv("GRAFTCACHE_RESULTS", str(results))
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])))
    monkeypatch.setenv("MPLBACKEND", "agg")
    nb = nbformat.read(NOTEBOOK, as_version=4)
    params = nb.cells[1].source
    assert "BOOTSTRAP = {}" in params, "the parameter cell no longer sets BOOTSTRAP"
    nb.cells[1].source = params.replace("BOOTSTRAP = {}", f'BOOTSTRAP = {{"n_boot": {n_boot}}}')
    nbclient.NotebookClient(nb, timeout=300, kernel_name="python3",
                            resources={"metadata": {"path": str(workdir)}}).execute()
    outputs = [o for c in nb.cells if c.cell_type == "code" for o in c.outputs]
    return Executed(text="".join(o.get("text", "") for o in outputs if o.output_type == "stream"),
                    errors=[o for o in outputs if o.output_type == "error"],
                    figures=sum("image/png" in o.get("data", {}) for o in outputs))
