"""Every notebook in notebooks/ runs top to bottom (so none can rot), in its quick setting.

The notebooks read ``JAXBVH_QUICK=1`` and shrink their inputs (fewer meshes, rays,
passes); the committed copies keep their full-size outputs, and this test never writes
to them: it executes a copy in memory. The kernels share the suite's persistent
compilation cache (``cache_dir``: the kernel inherits the environment, from which JAX
reads its cache settings), so programs one notebook compiled load in the next.
"""

from __future__ import annotations

import pytest
from helpers import REPO

NOTEBOOKS = sorted((REPO / "notebooks").glob("*.ipynb"))


def test_there_are_notebooks():
    assert len(NOTEBOOKS) >= 3


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_notebook_runs(path, monkeypatch, cache_dir):
    nbformat = pytest.importorskip("nbformat")
    nbclient = pytest.importorskip("nbclient", reason="the test extra installs nbclient")
    pytest.importorskip("ipykernel", reason="the test extra installs ipykernel")
    monkeypatch.setenv("JAXBVH_QUICK", "1")
    monkeypatch.setenv("MPLBACKEND", "Agg")
    notebook = nbformat.read(path, as_version=4)
    first = next(c for c in notebook.cells if c.cell_type == "code")
    assert "JAXBVH_QUICK" in first.source, f"{path.name}: the first code cell must read JAXBVH_QUICK"
    client = nbclient.NotebookClient(notebook, timeout=600, kernel_name="python3",
                                     resources={"metadata": {"path": str(path.parent)}})
    client.execute()  # raises CellExecutionError naming the cell that failed
    errors = [o for c in notebook.cells if c.cell_type == "code" for o in c.get("outputs", [])
              if o.get("output_type") == "error"]
    assert not errors
