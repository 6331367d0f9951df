# The two set-up commands of the README. Each creates .venv, installs the pinned local CPU torch
# first (an unpinned torch would pull gigabytes of CUDA packages), then the package.
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
OUT ?= results/windy-fig2-quick

.PHONY: demo test test-fast notebooks install install-test lint clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --upgrade pip

install: $(BIN)/python
	$(BIN)/python -m pip install torch==2.13.0
	$(BIN)/python -m pip install -e .

install-test: $(BIN)/python
	$(BIN)/python -m pip install torch==2.13.0
	$(BIN)/python -m pip install -e ".[test,distributed]"
	touch $(VENV)/.test-extras

# test-fast installs the test extras only on a fresh venv or after pyproject.toml changed
$(VENV)/.test-extras: pyproject.toml
	$(MAKE) install-test

## demo: install everything and run the main job (train, evaluate, print the table, write the plot);
## --overwrite: a rerun replaces the previous demo's results in $(OUT)
demo: install
	$(BIN)/taskvar experiment windy-fig2 --quick --overwrite --out $(OUT)

## test: install the test extras, check lint and formatting, run the whole suite, slow tests
## included, with a timeout per test, and print the 20 slowest (what .ci/run calls)
test: install-test
	$(BIN)/ruff check taskvar_torch tests benchmarks scripts
	$(BIN)/ruff format --check taskvar_torch tests benchmarks scripts
	$(BIN)/python -m pytest -q --durations=20

## test-fast: the developer's loop, under two minutes on a 2-core CPU: lint and formatting, then
## every test not marked slow (-m "not slow"); installs the test extras only when needed
test-fast: $(VENV)/.test-extras
	$(BIN)/ruff check taskvar_torch tests benchmarks scripts
	$(BIN)/ruff format --check taskvar_torch tests benchmarks scripts
	$(BIN)/python -m pytest -q -m "not slow" --durations=10

## notebooks: install the test extras (nbclient, ipykernel) and execute the four notebooks with
## small settings (tests/test_notebooks.py; each notebook's table lists its TASKVAR_NB_* knobs)
notebooks: install-test
	$(BIN)/python -m pytest -q tests/test_notebooks.py

## lint: the lint and format checks of make test, without installing or testing
lint:
	$(BIN)/ruff check taskvar_torch tests benchmarks scripts
	$(BIN)/ruff format --check taskvar_torch tests benchmarks scripts

clean:
	rm -rf $(VENV) results .pytest_cache
