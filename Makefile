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

.PHONY: all test test-slow lint bench clean-results browser lock

all: $(STAMP)
	$(BIN)/snakemake --cores $(CORES) --rerun-incomplete all

# Two workers (pytest-xdist), each test file whole on one of them: the suite's files share no
# paths (each test writes under its own tmp_path). TEST_WORKERS=0 runs it in one process.
TEST_WORKERS ?= 2
test: $(STAMP) browser
	$(BIN)/python -m pytest -n $(TEST_WORKERS) --dist loadfile

# The tests marked slow (left out of `make test` to keep it under 15 minutes on 2 cores).
test-slow: $(STAMP)
	$(BIN)/python -m pytest -m slow

# The browser tests of `refflow gui` drive Debian's chromium through its chromium-driver:
# installed here where the machine allows it (root and apt-get); elsewhere they skip and say why.
browser:
	@if command -v chromedriver >/dev/null 2>&1 && { command -v chromium || command -v chromium-browser; } >/dev/null 2>&1; then :; \
	elif [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then \
	  echo "installing chromium and chromium-driver for the browser tests (apt-get)"; \
	  { apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium chromium-driver >/dev/null; } \
	    || echo "could not install chromium: the browser tests will skip"; \
	else echo "no chromium/chromedriver and no root apt-get to install them: the browser tests will skip"; fi

lint: $(STAMP)
	$(BIN)/ruff check sim flow analysis refflow tests benchmarks
	$(BIN)/snakemake --lint

bench: $(STAMP)
	for b in benchmarks/bench_*.py; do $(BIN)/python $$b || exit 1; done

# Re-install only when the project's dependencies change. requirements.lock pins every
# package's version (pip freeze of a working .venv): newer releases of the dependencies
# changed the workbench's numbers with the same code (which package did is not known), and
# results/ must regenerate exactly.
# Refresh it deliberately: `make lock` in an up-to-date .venv, then regenerate results/.
$(STAMP): pyproject.toml requirements.lock
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet -c requirements.lock -e '.[test]'
	@echo "compiling the numba kernels of refflow's default method (once, about 30 s)"
	$(BIN)/python -c "from flow.methods.deepflow.method import compile_kernels; compile_kernels()"
	touch $(STAMP)

# Pin what .venv has now (run after a deliberate upgrade, then `make all` to regenerate results/).
lock:
	$(BIN)/python -m pip freeze --exclude-editable | grep -v '^refflow' > requirements.lock
