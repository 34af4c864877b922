# Two commands do everything on a fresh machine (Python 3.11 with venv):
#   make demo   create/refresh .venv, install everything, run the main job
#   make test   create/refresh .venv, install everything, lint (ruff check, ruff format --check), run the suite
#               (CI runs exactly this); make test-extended: the few checks it leaves out; make test-all: both
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: demo lint test test-extended test-all bench joint-space venv clean

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade "pip==25.3"
	# torch first, from the CPU wheel (PyPI's default torch is a multi-GB CUDA build)
	$(PY) -m pip install --quiet "torch==2.13.0"
	$(PY) -m pip install --quiet -e ".[dev]"
	touch $(STAMP)

venv: $(STAMP)

demo: $(STAMP)
	$(PY) -m jaxlimits.training.cli main --out results/main

# two pytest-xdist workers (the CI machine has 2 cores; XLA's CPU work is mostly single-threaded),
# whole files per worker, the slowest files first (tests/conftest.py); the `extended` tier (checks the
# suite or the campaign already covers, ~70 s of CPU) is left out of `make test` (CI), run by `make test-extended`
PYTEST := $(PY) -m pytest -q -n 2 --dist loadfile --no-loadscope-reorder
lint: $(STAMP)
	$(PY) -m ruff check .
	$(PY) -m ruff format --check .

test: lint
	$(PYTEST) -m "not extended"

test-extended: $(STAMP)
	$(PYTEST) -m extended

test-all: lint
	$(PYTEST)

bench: $(STAMP)
	$(PY) benchmarks/bench_bounds.py

joint-space: $(STAMP)
	$(PY) -m jaxlimits.training.cli joint-space --out results/joint_space

clean:
	rm -rf $(VENV) results .pytest_cache .hypothesis
