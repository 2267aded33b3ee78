# `make demo` and `make test` work on a fresh machine: they create .venv and install the project
# (--no-compile: Python compiles the modules it imports, not every module of every dependency).
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
export MUJOCO_GL ?= egl

.PHONY: demo test test-fast bench docs lint clean

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --no-compile -e ".[mujoco,vision,dev]"
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/python -m cldyn demo --overwrite
	$(BIN)/python -m keyvision demo --overwrite

lint: $(STAMP)
	$(BIN)/ruff check cldyn keyvision tests benchmarks examples docs

# --dist loadfile: a module's tests run on one worker, so what they compile in common (a scene's
# nominal model, a fixture's training) is compiled once, not on both workers (the tests' durations
# summed to 1808 s against 1909 s with tests spread one by one, 2026-11-26; wall times of one tree
# differ here by up to 7% from run to run). A worker that crashes ends the run: the replacement xdist
# starts is never given the lost tests, and the run would hang until CI's limit.
test: lint
	$(BIN)/python -m pytest -q -n 2 --dist loadfile --max-worker-restart 0

test-fast: $(STAMP)
	$(BIN)/python -m pytest -q -m "not slow"

bench: $(STAMP)
	$(BIN)/python -m pip install --quiet --no-compile -e ".[bench]"
	$(BIN)/python benchmarks/acceleration.py
	$(BIN)/python benchmarks/throughput.py

docs: $(STAMP)
	NO_MKDOCS_2_WARNING=1 $(BIN)/mkdocs build --strict --site-dir site

clean:
	rm -rf $(VENV) build dist *.egg-info
