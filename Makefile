# Two commands on a fresh machine: `make run` and `make test`. Every install step lives here.
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
OUT    ?= out

.PHONY: install run test lint types unit bench demo clean

install: $(STAMP)

# Re-install only when the project metadata or the pins change.
$(STAMP): pyproject.toml constraints.txt
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -c constraints.txt -e '.[dev]'
	touch $(STAMP)

# Until the acquisition server exists, `make run` runs the merge demo on a synthetic mosaic.
run: demo

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

unit: install
	$(BIN)/pytest -n 2 -q

test: lint types unit

bench: install
	$(BIN)/python benchmarks/merge_bench.py
	$(BIN)/python benchmarks/sim_bench.py

clean:
	rm -rf $(VENV) $(OUT) .mypy_cache .ruff_cache .pytest_cache
