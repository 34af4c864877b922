"""Execute every notebook in ``notebooks/`` (sorted) and fail on any cell error.

The notebooks are stored without outputs; this runs them top to bottom in a fresh ``python3``
kernel (this interpreter's ipykernel) with the notebooks folder as working directory and the
environment inherited from the test process plus ``JAXLIMITS_NOTEBOOK_QUICK=1`` (notebooks that
train use tiny budgets then).
"""

from pathlib import Path

import nbformat
import pytest
from nbclient import NotebookClient

NOTEBOOK_DIR = Path(__file__).resolve().parents[1] / "notebooks"
NOTEBOOKS = sorted(NOTEBOOK_DIR.glob("*.ipynb"))


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.name for p in NOTEBOOKS])
def test_notebook_executes(path, monkeypatch):
    monkeypatch.setenv("JAXLIMITS_NOTEBOOK_QUICK", "1")  # inherited by the kernel
    nb = nbformat.read(path, as_version=4)
    client = NotebookClient(
        nb,
        timeout=300,
        kernel_name="python3",
        resources={"metadata": {"path": str(path.parent)}},
    )
    client.execute()  # raises CellExecutionError (with the traceback) on the first failing cell
