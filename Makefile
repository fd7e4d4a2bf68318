# hdmap: one command to set up, one to test. Nothing needs sourcing; see README.md "Quick start".
SHELL := /bin/bash
.DEFAULT_GOAL := help

VENV   := .venv
PYTHON := $(VENV)/bin/python
PYTEST_ARGS ?=

# DDS stays on this machine (Fast DDS would otherwise send discovery multicast out of the
# network interface) and in its own domain. Override on the command line if needed.
export ROS_AUTOMATIC_DISCOVERY_RANGE ?= LOCALHOST
export ROS_DOMAIN_ID ?= 42

.PHONY: help setup test test-quick lint demo bench constraints clean

help:  ## list the targets
	@grep -E '^[a-z-]+:.*## ' $(MAKEFILE_LIST) | awk -F':.*## ' '{printf "  make %-12s %s\n", $$1, $$2}'

setup:  ## create .venv, install pinned ROS 2 wheels + deps, colcon build (idempotent)
	@bash scripts/setup.sh

test: lint  ## lint (make lint), then the whole pytest suite
	$(PYTHON) -m pytest $(PYTEST_ARGS)

test-quick: setup  ## the suite without tests marked slow (no lint: the edit-test loop)
	$(PYTHON) -m pytest -m "not slow" $(PYTEST_ARGS)

lint: setup  ## ruff check, ruff format --check (whole tree), mypy on src/hdmap_core (ruff.toml, mypy.ini)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check --output-format concise .
	$(VENV)/bin/mypy

demo: setup  ## simulate a fleet, build a map, evaluate it (scripts/demo.sh)
	@bash scripts/demo.sh

bench: setup  ## benchmarks (scripts/bench.sh)
	@bash scripts/bench.sh

constraints:  ## re-pin constraints.txt from the working .venv
	$(PYTHON) scripts/write_constraints.py > constraints.txt

clean:  ## remove the colcon build (build/ install/ log/); keeps .venv
	rm -rf build install log
