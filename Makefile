# Two commands on a fresh machine: `make run` and `make test`. Every install step lives here.
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
OUT    ?= out

.PHONY: install run test lint types unit browser bench demo docs clean

# The project's own modules compiled once here: a shell with PYTHONDONTWRITEBYTECODE set would
# otherwise compile them again at every start (~0.1 s of every CLI call).
install: $(STAMP)
	@$(BIN)/python -m compileall -q backend hardware merge

# Re-install only when the project metadata or the pins change.
$(STAMP): pyproject.toml constraints.txt
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -c constraints.txt -e '.[dev]'
	touch $(STAMP)

# The acquisition server on the simulated instrument (migrates the database at start-up).
HOST ?= 127.0.0.1
PORT ?= 8000
DATA ?= data

run: install
	@echo "Starting the Mosaic AFM server on the simulated instrument (MOSAIC_* variables change it, see README);"
	@echo "it prints the URLs of the pages, the API docs and the 3D viewer, and the API token at first start."
	$(BIN)/mosaic-afm serve --host $(HOST) --port $(PORT) --data-dir $(DATA)

demo: install
	$(BIN)/mosaic-afm synth --out $(OUT)/demo-patches --surface chessboard --seed 1
	$(BIN)/mosaic-afm merge $(OUT)/demo-patches/manifest.json --out $(OUT)/demo-merge
	@echo "Merged mosaic: $(OUT)/demo-merge/mosaic.npy, preview: $(OUT)/demo-merge/preview.png"

lint: install
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/lint-imports

types: install
	$(BIN)/mypy

unit: install browser
	$(BIN)/pytest -n 2 --dist loadgroup -q --durations=20

# System programs the tests use: Debian's chromium for the browser tests (Playwright's own
# download does not work here) and gwyddion, the oracle of every format's orientation.
browser:
	@missing=""; \
	command -v chromium >/dev/null 2>&1 || missing="$$missing chromium"; \
	command -v gwyddion >/dev/null 2>&1 || missing="$$missing gwyddion"; \
	if [ -n "$$missing" ]; then \
	  echo "installing Debian's$$missing for the tests"; \
	  SUDO=$$( [ "$$(id -u)" -eq 0 ] || echo sudo ); \
	  $$SUDO apt-get update -q && $$SUDO apt-get install -y -q $$missing; \
	fi

# The documentation site (docs/_build/html/index.html): every warning is an error, the
# gallery's examples run and make their figures.
docs: install
	$(BIN)/sphinx-build -W --keep-going -q -b html docs docs/_build/html
	@echo "The documentation: docs/_build/html/index.html"

test: lint types unit docs

bench: install
	$(BIN)/python benchmarks/merge_bench.py --quick --sweep 10 --gratings 10
	$(BIN)/python benchmarks/merge_scale.py --bound
	$(BIN)/python benchmarks/merge_variations.py
	$(BIN)/python benchmarks/crb.py --noise-draws 12
	$(BIN)/python benchmarks/sim_bench.py
	$(BIN)/python benchmarks/nanonis_bench.py
	$(BIN)/python benchmarks/server_bench.py
	$(BIN)/python benchmarks/safety_bench.py
	$(BIN)/python benchmarks/sem_bench.py
	$(BIN)/python benchmarks/correlative_bench.py
	$(BIN)/python benchmarks/viewer_bench.py
	$(BIN)/python benchmarks/live_bench.py
	$(BIN)/python benchmarks/access_bench.py

clean:
	rm -rf $(VENV) $(OUT) .mypy_cache .ruff_cache .pytest_cache docs/_build docs/_generated docs/auto_examples
