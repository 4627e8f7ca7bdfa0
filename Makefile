# Two commands do all the set-up: `make demo` and `make test` (see README.md).
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
comma := ,

.PHONY: demo test lint docs install lock bench clean

$(BIN)/python:
	$(PY) -m venv $(VENV)

# uv installs what pip would (`uv pip install`, the same pins; 10 s here against pip's 55 s), from the
# package locations pip is configured with (pip config: index-url, extra-index-url, find-links), taking
# the best version across them as pip does; where uv cannot be installed, pip does it all
define UV_FLAGS_PY
import subprocess, sys
listed = subprocess.run([sys.executable, "-m", "pip", "config", "list"], capture_output=True, text=True).stdout
pairs = {}
for line in listed.splitlines():
    key, _, value = line.partition("=")
    option = key.rsplit(".", 1)[-1]
    if option in ("index-url", "extra-index-url", "find-links"):
        pairs.update({(option, v): None for v in value.strip("'\"").split()})
print(" ".join([f"--{o} {v}" for o, v in pairs] + ["--index-strategy unsafe-best-match"]))
endef
export UV_FLAGS_PY
UV := $(BIN)/uv pip install -q --python $(BIN)/python

# torch first and pinned: 2.13.0 is the CPU build on this machine's disk; then everything else
# at the versions of constraints.txt, the resolved set the tests passed with. No byte code at install
# (an installer compiles every file, one at a time): the modules the suite and the demo import, a fifth of the
# 18,700 files, are compiled by importing them, in two processes side by side (25 s of compileall on
# every core -> 10 s from a fresh clone); a module first imported later is compiled then, once. The
# byte code must be written: where PYTHONDONTWRITEBYTECODE is set nothing imported is ever cached.
WARM_TORCH := atdrone.service.actors atdrone.learn.trainer atdrone.deploy.job atdrone.benchmark.report \
	torch._dynamo hypothesis
WARM_REST := atdrone.cli atdrone.tracking atdrone.registry atdrone.service.driver mlflow.tracking \
	mlflow.store.tracking.sqlalchemy_store mlflow.store.model_registry.sqlalchemy_store matplotlib.pyplot \
	pettingzoo gymnasium pytest xdist ray.util.state ray.dashboard.agent ray.dashboard.dashboard \
	ray.dashboard.head ray.autoscaler._private.monitor ray._private.log_monitor
$(STAMP): pyproject.toml constraints.txt | $(BIN)/python
	if [ -x $(BIN)/uv ] || $(BIN)/pip install -q uv==0.13.9; then \
	  flags=$$($(BIN)/python -c "$$UV_FLAGS_PY") && $(UV) $$flags torch==2.13.0 && \
	  $(UV) $$flags -c constraints.txt -e ".[dev,deploy]"; \
	else \
	  $(BIN)/pip install -q --no-compile torch==2.13.0 && \
	  $(BIN)/pip install -q --no-compile -c constraints.txt -e ".[dev,deploy]"; \
	fi
	PYTHONDONTWRITEBYTECODE= $(BIN)/python -c "import $(subst $() ,$(comma),$(WARM_TORCH))" & w=$$!; \
	PYTHONDONTWRITEBYTECODE= $(BIN)/python -c "import $(subst $() ,$(comma),$(WARM_REST))" && wait $$w
	touch $(STAMP)

install: $(STAMP)

# re-resolve from pyproject.toml's ranges and record the result in constraints.txt
lock: | $(BIN)/python
	$(BIN)/pip install -q torch==2.13.0
	$(BIN)/pip install -q --upgrade -e ".[dev,deploy]"
	{ echo "# The resolved dependency set the tests passed with (regenerate with: make lock)."; \
	  echo "# make install uses it as pip constraints, so a fresh clone installs these versions."; \
	  $(BIN)/pip freeze --exclude-editable | grep -v '^atdrone' | sed 's/^torch==\(.*\)+cpu$$/torch==\1/'; \
	} > constraints.txt.tmp && mv constraints.txt.tmp constraints.txt

lint: $(STAMP)
	$(BIN)/ruff check atdrone tests benchmarks jobs
	$(BIN)/ruff format --check atdrone tests benchmarks jobs
	$(BIN)/mypy

# the docs/ site; --strict: a broken link, anchor or a page left out of the nav fails
docs: $(STAMP)
	$(BIN)/mkdocs build --strict --quiet

# the type check runs beside the test sessions (half a minute of one core from a fresh clone); each session
# ends with its 25 slowest tests
test: docs
	$(BIN)/ruff check atdrone tests benchmarks jobs
	$(BIN)/ruff format --check atdrone tests benchmarks jobs
	$(BIN)/python tests/run_suite.py --beside $(BIN)/mypy --durations=25

# the quick HOLA-Drone V2 run on a local Ray, in runs/hola_quick (<= 10 min on 2 cores); run again, it
# resumes an interrupted run or shows the finished one
demo: $(STAMP)
	$(BIN)/atdrone train configs/experiments/hola_quick.json --resume

bench: $(STAMP)
	$(BIN)/python benchmarks/env_throughput.py

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache site
