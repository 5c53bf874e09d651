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

# uv installs the same pinned set as pip in a third of the time (14 s against 40 s on a 2-core machine: it fetches
# in parallel); it reads no pip configuration, so where it cannot reach the index (a mirror set in pip.conf) pip
# installs instead. Neither byte-compiles (pip: --no-compile): that cost half of pip's install, and Python
# compiles what it imports on first use.
EXTRAS := .[dev,flight,interfaces,wandb,optuna]
$(STAMP): pyproject.toml constraints.txt
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q -c constraints.txt uv
	$(VENV)/bin/uv pip install -q --python $(PY) -c constraints.txt -e '$(EXTRAS)' \
		|| $(PY) -m pip install -q --no-compile -c constraints.txt -e '$(EXTRAS)'
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
