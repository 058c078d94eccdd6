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

# two pytest workers, one torch thread each (the 2-core machine's cores); a test file stays on one worker, so its
# module fixtures are built once. TEST_WORKERS=0 runs in this process.
TEST_WORKERS ?= 2
test: setup
	OMP_NUM_THREADS=1 $(PY) -m pytest -q -n $(TEST_WORKERS) --dist loadfile

test-slow: setup
	$(PY) -m pytest -q -m slow

# the lab's probes' tests (lab/), not part of `make test`
test-lab: setup
	$(PY) -m pytest -q lab

bench: setup
	$(PY) benchmarks/planner.py

clean:
	rm -rf $(DEMO_OUT) .pytest_cache
