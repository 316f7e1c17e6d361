# The two commands of the README: `make demo` and `make test`. Both set up .venv first.
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
# DESIGN.md §7: a bare `torch` pulls the newest CUDA build (gigabytes); torch==2.13.0 takes the
# local CPU wheel on the project's machines. Elsewhere override, e.g. `make test TORCH_SPEC=torch`.
TORCH_SPEC ?= torch==2.13.0
PYTEST_ARGS ?=
# `make test` runs the suite in this many pytest-xdist worker processes, one test file per worker at a
# time (--dist loadfile keeps each file's module fixtures, e.g. its private dataset cache, in one
# process). 2 suits the project's 2-core machines (16.5 -> 11.5 min there, session 28; 7 min since session 43, docs/architecture.md "Tests"); 0 runs serially.
TEST_WORKERS ?= 2

.PHONY: setup demo test test-slow lint bench clean FORCE

STAMP := $(VENV)/.installed
# The TORCH_SPEC the venv was installed with, written by the install below.
SPEC_FILE := $(VENV)/.torch-spec
# Besides its prerequisites' dates, an existing stamp is stale when the venv's python no longer runs (its base
# interpreter upgraded or removed leaves bin/python3 a dangling link, and `test -x` on the venv never noticed) or when
# it was installed with another TORCH_SPEC (`make test TORCH_SPEC=torch` on an existing .venv did nothing). Both are
# read when make starts, not in a recipe, so that `make -q setup` and `make -n` tell the truth and an up-to-date venv
# costs one python start, never a pip run.
ifneq ($(wildcard $(STAMP)),)
ifeq ($(shell $(BIN)/python -c '' >/dev/null 2>&1 && echo runs),)
SETUP_STALE := FORCE
endif
ifneq ($(shell cat $(SPEC_FILE) 2>/dev/null),$(strip $(TORCH_SPEC)))
SETUP_STALE := FORCE
endif
endif

setup: $(STAMP)

$(STAMP): pyproject.toml Makefile $(SETUP_STALE)
	$(BIN)/python -c '' 2>/dev/null || { rm -rf $(VENV) && $(PYTHON) -m venv $(VENV); }
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q "$(TORCH_SPEC)"
	$(BIN)/python -m pip install -q -e ".[dev]"
	printf '%s\n' '$(TORCH_SPEC)' > $(SPEC_FILE)
	touch $@

FORCE:

demo: setup
	$(BIN)/hsicam demo --out runs/demo

test: setup
	$(BIN)/python -m pytest -q -m "not slow" -n $(TEST_WORKERS) --dist loadfile $(PYTEST_ARGS)

test-slow: setup
	$(BIN)/python -m pytest -q -m slow $(PYTEST_ARGS)

# Static checks of src/ (the rules in pyproject.toml's [tool.ruff.lint]) and pyflakes on the tests, benchmarks and
# scripts (unused imports and never-read values, a forgotten assertion's mark; F811 left out: a test module imports
# its fixtures, which its tests then name as parameters) with this ruff, installed into the venv here only (not a dev
# extra); not part of `make test`.
RUFF_VERSION ?= 0.17.6

lint: setup
	$(BIN)/ruff --version 2>/dev/null | grep -qx 'ruff $(RUFF_VERSION)' || $(BIN)/python -m pip install -q "ruff==$(RUFF_VERSION)"
	$(BIN)/ruff check src
	$(BIN)/ruff check --select F --ignore F811 tests benchmarks scripts

bench: setup
	$(BIN)/python benchmarks/bench_camera.py
	$(BIN)/python benchmarks/bench_data.py
	$(BIN)/python benchmarks/bench_cli.py

clean:
	rm -rf $(VENV) runs .pytest_cache .ruff_cache build src/*.egg-info
