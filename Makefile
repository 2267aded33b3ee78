# `make demo` and `make test` work on a fresh machine: they create .venv and install the project.
# --no-compile, then bytecode for the modules that the project, its tests and its CLIs import (about
# 1,300 files, 10 s once at install, 2026-11-27), not for every module of every dependency: where
# PYTHONDONTWRITEBYTECODE is set (as on the machine this project is developed on) Python never writes
# the bytecode it compiles on import, and every process (a CLI command, a test worker, a test's
# subprocess, a render worker) spent about 3 s of its 5 s of imports compiling the same sources again.
# A module that fails to import here is left out (the tests will say why); the install goes on.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
export MUJOCO_GL ?= egl

define PRECOMPILE
import importlib, py_compile, sys, warnings
warnings.simplefilter("ignore")
for name in ("cldyn", "cldyn.mujoco", "keyvision", "matplotlib.pyplot", "imageio.v3", "dm_control.suite",
             "pytest", "xdist"):
    try:
        importlib.import_module(name)
    except Exception as error:
        print(f"precompile: {name} does not import ({error}); left out", file=sys.stderr)
for module in list(sys.modules.values()):
    source = getattr(module, "__file__", None) or ""
    if source.endswith(".py"):
        try:
            py_compile.compile(source, doraise=True)  # into __pycache__, where imports look
        except (OSError, py_compile.PyCompileError):
            pass  # a read-only or odd source: Python compiles it on import as before
endef
export PRECOMPILE

.PHONY: demo test test-fast bench docs lint clean

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --no-compile -e ".[mujoco,vision,dev]"
	$(BIN)/python -c "$$PRECOMPILE"
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/python -m cldyn demo --overwrite
	$(BIN)/python -m keyvision demo --overwrite

lint: $(STAMP)
	$(BIN)/ruff check cldyn keyvision tests benchmarks examples docs

# --dist loadfile: a module's tests run on one worker, so what they compile in common (a scene's
# nominal model, a fixture's training) is compiled once, not on both workers (the tests' durations
# summed to 1808 s against 1909 s with tests spread one by one, 2026-11-26; wall times of one tree
# differ here by up to 20% from run to run: 815, 840 and 982 s for one tree on 2026-11-28). A worker
# that crashes ends the run: the replacement xdist starts is never given the lost tests, and the run
# would hang until CI's limit.
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
