# The README's two commands. Both bootstrap .venv from the machine's python3
# and are quick when it is already up to date.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
CORES ?= all
# Rules call `python`, `refflow` and `snakemake`: the ones in .venv.
export PATH := $(CURDIR)/$(BIN):$(PATH)
export PYOPENGL_PLATFORM ?= egl
export MPLBACKEND ?= Agg

.PHONY: all test lint bench clean-results

all: $(STAMP)
	$(BIN)/snakemake --cores $(CORES) --rerun-incomplete all

test: $(STAMP)
	$(BIN)/python -m pytest

lint: $(STAMP)
	$(BIN)/ruff check sim flow analysis refflow tests benchmarks
	$(BIN)/snakemake --lint

bench: $(STAMP)
	for b in benchmarks/bench_*.py; do $(BIN)/python $$b || exit 1; done

# Re-install only when the project's dependencies change.
$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet -e '.[test]'
	touch $(STAMP)
