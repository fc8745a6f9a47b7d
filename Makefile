# One-command entry points (README quick start). Everything installs into ./.venv.
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
EXTRAS ?= test

.PHONY: setup demo test warmup bench clean

$(BIN)/.installed-$(EXTRAS): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --upgrade pip
	$(BIN)/python -m pip install -e ".[$(EXTRAS)]"
	touch $@

setup: $(BIN)/.installed-$(EXTRAS)

## demo: set up and run the main job on built-in data
demo: setup
	$(BIN)/octomerge demo --out-dir octomerge-demo

## warmup: compile the merge kernels into the CLI's persistent cache (once; later merges start warm)
warmup: setup
	$(BIN)/octomerge warmup

## test: set up and run the test suite (what CI runs)
test: setup
	$(BIN)/python -m pytest -m "not slow" -n auto --dist loadfile

clean:
	rm -rf $(VENV) octomerge-demo .pytest_cache .hypothesis
