# Every target creates and reuses .venv on first use: nothing to type before `make train` or `make test`.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
SCENARIO ?= race
ARGS ?=

# Python writes the bytecode of what it imports (some shells set PYTHONDONTWRITEBYTECODE): without it every process
# compiles jax and its dependencies from source again, some 5 s each, and the tests start a dozen processes.
unexport PYTHONDONTWRITEBYTECODE

.PHONY: install train test bench bench-train bench-flight paper-table safety-matrix lint clean

# --no-compile: byte-compiling every installed module costs half the install (29 s against 58 s here); Python
# compiles what it imports on first use.
$(STAMP): pyproject.toml constraints.txt
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q --no-compile -c constraints.txt -e '.[dev,flight,interfaces,wandb,optuna]'
	touch $(STAMP)

install: $(STAMP)

# CONFIG=FILE trains from a config file (its scenario is the file's); else SCENARIO (default race).
train: $(STAMP)
	$(VENV)/bin/aswarm train $(if $(CONFIG),--config $(CONFIG),--scenario $(SCENARIO)) $(ARGS)

test: $(STAMP)
	$(PY) -m pytest -q -n 2 --dist loadfile --durations=20

bench: $(STAMP)
	$(VENV)/bin/aswarm bench --peer-venv .venv-crazyflow $(ARGS)

bench-train: $(STAMP)
	$(VENV)/bin/aswarm bench --trainer $(ARGS)

bench-flight: $(STAMP)
	$(PY) -m aswarm.flight.bench --out BENCHMARKS.md $(ARGS)

paper-table: $(STAMP)
	$(PY) experiments/paper_table.py $(ARGS)

# make safety-matrix ARGS="--policy obstacles=runs/obstacles-m13": every cell of issue #13 (hours; re-run to resume)
safety-matrix: $(STAMP)
	$(PY) experiments/safety_matrix.py $(ARGS)

lint: $(STAMP)
	$(VENV)/bin/ruff check aswarm tests experiments

clean:
	rm -rf $(VENV) .venv-crazyflow .pytest_cache .ruff_cache *.egg-info build
	find . -name __pycache__ -type d -prune -exec rm -rf {} +

sweep: $(STAMP)
	$(VENV)/bin/aswarm sweep $(SWEEP) $(ARGS)

# make sweep SWEEP=sweeps/race_lr.toml: a hyperparameter sweep in one program (re-run to resume)
SWEEP ?= sweeps/race_lr.toml
.PHONY: sweep
