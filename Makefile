# The two set-up commands of the README. Each creates .venv, installs the pinned local CPU torch
# first (an unpinned torch would pull gigabytes of CUDA packages), then the package.
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
OUT ?= results/windy-fig2-quick
DEMO ?= results/demo
DEMO_FRAMES := 10240
WORKERS ?= 2
PYTEST = OMP_NUM_THREADS=1 MKL_NUM_THREADS=1 OMP_WAIT_POLICY=PASSIVE $(BIN)/python -m pytest -q -n $(WORKERS) \
	--dist loadfile --no-loadscope-reorder
DEMO_TRAIN := train.total_frames=$(DEMO_FRAMES) train.eps_decay_frames=6000 \
	train.init_random_frames=1024 train.checkpoint_every=0

.PHONY: demo fig2 results test test-fast notebooks install install-test lint clean

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

## demo: install everything, then on the windy corridor (configs/windy_corridor.yaml, docs/memory.md)
## train the paper's heads, then the recurrent, informed and blind baselines (10240 frames each), and evaluate
## every method on 2000 paired episodes of the training winds: the table puts each method's return
## and exact value beside the exact per-instance optimum (the ceiling) and its regret, and --explain
## says what it shows, from its numbers; the plots go to $(DEMO)/eval. The first lines say what is
## compared and what to look for. Measured on 2 CPU cores: see the README; a rerun replaces $(DEMO)
demo: install
	@echo "== make demo: memory against the paper's methods on the windy corridor (configs/windy_corridor.yaml)"
	@echo "Each episode hides a wind from the agent: strength p in [0, 1], blowing north or south. From the"
	@echo "start cell S, between two windy cells, it must reach an exit at either end. A gust that pushes it"
	@echo "back to S tells the wind's direction, which only a policy with memory can use. Exact on this layout:"
	@echo "the best memoryless policy returns -2.0 per episode (a stochastic one, which greedy Q-heads cannot"
	@echo "represent), the best with memory -1.833, one that knows the wind -1.5 (docs/memory.md)."
	@echo "Compared on the same 2000 episodes: the paper's memoryless methods (averaging, options,"
	@echo "interruption), a recurrent policy (memory), blind (the same learner with no memory: its control)"
	@echo "and informed, which sees the hidden wind."
	@echo "Look at the last table's regret column: steps per episode lost to an agent that knows the wind."
	@echo "The budget is small ($(DEMO_FRAMES) frames per model): the training lines compare the heads with the"
	@echo "exact oracle and name what is not learnt yet. Three steps, each command printed as it starts:"
	@echo "taskvar train (the paper's heads), taskvar train-baselines (recurrent, informed and blind, each"
	@echo "on its own stream, same budget), taskvar eval --explain (every method on 2000 paired episodes)."
	$(BIN)/taskvar train configs/windy_corridor.yaml --overwrite --out $(DEMO) $(DEMO_TRAIN)
	$(BIN)/taskvar train-baselines --out $(DEMO) --method all --overwrite
	$(BIN)/taskvar eval --checkpoint $(DEMO)/final.pt --method all --test train --episodes 2000 \
		--overwrite --out $(DEMO)/eval --explain
	@echo "Next: make fig2 (the paper's Figure 2 protocol: interruption vs averaging); notebooks/ (read"
	@echo "rendered); docs/results.md (every family, many training seeds)"

## fig2: install everything and run the paper's Figure 2 protocol, quick (train, evaluate, print the
## table, write the plot); --overwrite: a rerun replaces the previous results in $(OUT)
fig2: install
	$(BIN)/taskvar experiment windy-fig2 --quick --overwrite --out $(OUT)

## results: install everything and regenerate every Results row (docs/results.md) at this commit
## (scripts/results.py: each row's train, baselines and eval steps, then taskvar report; hours on
## 2 cores, so run it in the background; an interrupted run goes on where it stopped; RESULTS=DIR)
RESULTS ?= results/regen
results: install
	$(BIN)/python scripts/results.py --out $(RESULTS)

## test: install the test extras, check lint and formatting, run the whole suite, slow tests
## included, with a timeout per test, and print the 20 slowest (what .ci/run calls). The files
## run on $(WORKERS) pytest-xdist workers (whole files each, slow files first: tests/conftest.py),
## one torch thread each, OpenMP threads that sleep rather than spin when they wait (a test that
## asks for 2 threads beside the other worker ran 137 s instead of 3); WORKERS=0 runs them in this process
test: install-test
	$(BIN)/ruff check taskvar_torch tests benchmarks scripts
	$(BIN)/ruff format --check taskvar_torch tests benchmarks scripts
	$(PYTEST) --durations=20

## test-fast: the developer's loop, under two minutes on a 2-core CPU: lint and formatting, then
## every test not marked slow (-m "not slow"), on $(WORKERS) workers as make test; installs the
## test extras only when needed
test-fast: $(VENV)/.test-extras
	$(BIN)/ruff check taskvar_torch tests benchmarks scripts
	$(BIN)/ruff format --check taskvar_torch tests benchmarks scripts
	$(PYTEST) -m "not slow" --durations=10

## notebooks: install the test extras (nbclient, ipykernel), execute the four notebooks with the
## test suite's small settings (tests/test_notebooks.py SETTINGS; each notebook's table lists its
## TASKVAR_NB_* knobs) and store them with their outputs, plots included, for a reader to see
## without running them; commit the result. CI executes them again and fails where a stored output
## is stale. About 1.5 min on 2 CPU cores
notebooks: install-test
	TASKVAR_NB_WRITE=1 $(BIN)/python -m pytest -q tests/test_notebooks.py

## lint: the lint and format checks of make test, without installing or testing
lint:
	$(BIN)/ruff check taskvar_torch tests benchmarks scripts
	$(BIN)/ruff format --check taskvar_torch tests benchmarks scripts

clean:
	rm -rf $(VENV) results .pytest_cache
