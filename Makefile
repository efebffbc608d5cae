# make demo / make test create .venv from pyproject.toml on first use (and when it changes).
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed-stamp
export PREFECT_SERVER_ANALYTICS_ENABLED := false
export PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS ?= 180
export PREFECT_HOME ?= $(CURDIR)/.prefect

.PHONY: demo test test-all bench lint docs clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

demo: $(STAMP)  ## the main job on embedded defaults, outputs under ./data
	$(VENV)/bin/tcspc demo --out data

# the default suite runs on 2 workers (pytest-xdist): 385 s serial, 231 s on 2 on the 2-core VM
TEST_WORKERS ?= 2

test: $(STAMP)  ## the default suite (slow tests excluded), on TEST_WORKERS processes
	$(PY) -m pytest -q -n $(TEST_WORKERS)

test-all: $(STAMP)  ## everything, slow tests included
	$(PY) -m pytest -q -m ''

bench: $(STAMP)  ## benchmarks/datapath.py (add the peer with: pip install -e '.[bench]')
	$(PY) benchmarks/datapath.py

lint: $(STAMP)
	$(VENV)/bin/ruff check .

docs: $(STAMP)  ## regenerate docs/schemas.md, docs/cli.md and docs/operations.md's topology keys
	$(VENV)/bin/tcspc schema --markdown > docs/schemas.md
	$(PY) -m pipeline.cli.docs > docs/cli.md
	$(PY) -m pipeline.cli.docs --operations docs/operations.md

clean:
	rm -rf $(VENV) .prefect data .pytest_cache .hypothesis
