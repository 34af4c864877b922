"""Execute every notebook in ``notebooks/`` (sorted) and fail on any cell error.

The notebooks are stored without outputs; this runs them top to bottom in a fresh ``python3``
kernel (this interpreter's ipykernel) with the notebooks folder as working directory and the
environment inherited from the test process plus ``JAXLIMITS_NOTEBOOK_QUICK=1`` (notebooks that
train use tiny budgets then). ``06_training`` runs in the main job's test, on that job's results.
"""

import pytest
from conftest import NOTEBOOK_DIR, run_notebook

# run by another test, on that test's results (instead of training the same tiny run again here)
EXECUTED_ELSEWHERE = {
    "06_training.ipynb": "tests/test_training.py::test_main_job_train_evaluate_reload_on_a_tiny_budget"
}
NOTEBOOKS = [p for p in sorted(NOTEBOOK_DIR.glob("*.ipynb")) if p.name not in EXECUTED_ELSEWHERE]


def test_every_notebook_is_executed():
    assert {p.name for p in NOTEBOOKS} | set(EXECUTED_ELSEWHERE) == {p.name for p in NOTEBOOK_DIR.glob("*.ipynb")}
    root = NOTEBOOK_DIR.parent
    assert all(name in (root / test.split("::")[0]).read_text() for name, test in EXECUTED_ELSEWHERE.items())


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.name for p in NOTEBOOKS])
def test_notebook_executes(path, monkeypatch):
    run_notebook(path, monkeypatch)
