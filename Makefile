# Two commands for a fresh machine:
#   make demo   set up .venv and run the main job on a small default
#   make test   set up .venv and run the test suite (tiny meshes)
#   make slurm  add the optional 'slurm' extra (dask-jobqueue) to .venv, for workflows/slurm_cluster.py
SHELL := /bin/bash
VENV := .venv
PY := $(VENV)/bin/python
export UV_PYTHON_DOWNLOADS := never
export UV_COMPILE_BYTECODE := 1
export OMP_NUM_THREADS := 1
export OPENBLAS_NUM_THREADS := 1
export MKL_NUM_THREADS := 1

.PHONY: venv demo test lint format slurm

venv: $(VENV)/.installed

$(VENV)/.installed: pyproject.toml
	python3 -m pip install -q uv 2>/dev/null || python3 -m pip install -q --user uv
	python3 -m uv venv -q --allow-existing --python 3.12 $(VENV)
	python3 -m uv pip install -q --python $(PY) -e '.[dev]'
	touch $@

demo: venv
	$(VENV)/bin/elastimap demo

test: venv
	$(VENV)/bin/pytest -q -n 2 --dist loadgroup

lint: venv
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .

format: venv
	$(VENV)/bin/ruff check --fix .
	$(VENV)/bin/ruff format .

# A uv venv has no pip: `pip install -e '.[slurm]'` fails there; uv installs into it instead.
slurm: venv
	python3 -m uv pip install -q --python $(PY) -e '.[slurm]'
