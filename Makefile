# Two commands do all the set-up: `make demo` and `make test` (see README.md).
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test lint install bench clean

$(BIN)/python:
	$(PY) -m venv $(VENV)
	$(BIN)/pip install --upgrade pip -q

# torch first and pinned: 2.13.0 is the CPU build on this machine's disk
$(STAMP): pyproject.toml | $(BIN)/python
	$(BIN)/pip install -q torch==2.13.0
	$(BIN)/pip install -q -e ".[dev,deploy]"
	touch $(STAMP)

install: $(STAMP)

lint: $(STAMP)
	$(BIN)/ruff check atdrone tests benchmarks jobs
	$(BIN)/ruff format --check atdrone tests benchmarks jobs
	$(BIN)/mypy

test: lint
	$(BIN)/python -m pytest -q

# the quick HOLA-Drone V2 run on a local Ray (a fresh run name each time; <= 10 min on 2 cores)
demo: $(STAMP)
	$(BIN)/atdrone train configs/experiments/hola_quick.json --name hola_quick_$$(date +%Y%m%d_%H%M%S)

bench: $(STAMP)
	$(BIN)/python benchmarks/env_throughput.py

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache
