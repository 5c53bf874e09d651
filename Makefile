# Every target creates and reuses .venv on first use: nothing to type before `make train` or `make test`.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
SCENARIO ?= race
ARGS ?=

.PHONY: install train test bench bench-train lint clean

$(STAMP): pyproject.toml constraints.txt
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -c constraints.txt -e '.[dev]'
	touch $(STAMP)

install: $(STAMP)

train: $(STAMP)
	$(VENV)/bin/aswarm train --scenario $(SCENARIO) $(ARGS)

test: $(STAMP)
	$(PY) -m pytest -q

bench: $(STAMP)
	$(VENV)/bin/aswarm bench --peer-venv .venv-crazyflow $(ARGS)

bench-train: $(STAMP)
	$(VENV)/bin/aswarm bench --trainer $(ARGS)

lint: $(STAMP)
	$(VENV)/bin/ruff check aswarm tests experiments

clean:
	rm -rf $(VENV) .venv-crazyflow .pytest_cache .ruff_cache *.egg-info build
	find . -name __pycache__ -type d -prune -exec rm -rf {} +
