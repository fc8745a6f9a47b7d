# One-command entry points (README quick start). Everything installs into ./.venv.
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin

.PHONY: setup demo test warmup bench notebooks clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --upgrade pip

# the package alone: what `octomerge demo` needs
$(BIN)/.installed-core: pyproject.toml | $(BIN)/python
	$(BIN)/python -m pip install -e .
	touch $@

# the package with the test tool chain (pytest, OctoMap's Python bindings, viser, ...)
$(BIN)/.installed-test: pyproject.toml | $(BIN)/python
	$(BIN)/python -m pip install -e ".[test]"
	touch $@ $(BIN)/.installed-core

setup: $(BIN)/.installed-test

## demo: set up and run the main job on built-in data
demo: $(BIN)/.installed-core
	$(BIN)/octomerge demo --out-dir octomerge-demo

## warmup: compile the merge kernels into the CLI's persistent cache (once; later merges start warm)
warmup: setup
	$(BIN)/octomerge warmup

## test: set up and run the test suite (what CI runs)
test: $(BIN)/.installed-test
	$(BIN)/python -m pytest -m "not slow" -n auto --dist loadfile

## notebooks: execute the notebooks in place (committed with their outputs)
notebooks: $(BIN)/.installed-test
	$(BIN)/python notebooks/execute.py notebooks/*.ipynb

clean:
	rm -rf $(VENV) octomerge-demo .pytest_cache .hypothesis
