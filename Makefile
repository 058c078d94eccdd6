# Two entry points, both idempotent: `make demo` (set up, then the main job) and `make test`; `make test-lab` runs the lab's tests.
SHELL := /bin/bash
VENV ?= .venv
PY := $(VENV)/bin/python
WAMPLAN := $(VENV)/bin/wamplan
DEMO_OUT ?= out/demo

.PHONY: setup demo test test-slow test-lab bench clean

setup:
	@bash scripts/setup.sh

demo: setup
	@bash scripts/demo.sh $(DEMO_OUT)

test: setup
	$(PY) -m pytest -q

test-slow: setup
	$(PY) -m pytest -q -m slow

# the lab's probes' tests (lab/), not part of `make test`
test-lab: setup
	$(PY) -m pytest -q lab

bench: setup
	$(PY) benchmarks/planner.py

clean:
	rm -rf $(DEMO_OUT) .pytest_cache
