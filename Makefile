# tiereg — set-up, demo, tests and benchmarks. Everything installs into .venv.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed-$(shell cat pyproject.toml | cksum | cut -d' ' -f1)

.PHONY: install demo test bench bench-quick clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip

$(STAMP): $(BIN)/python pyproject.toml
	$(BIN)/python -m pip install --quiet -e '.[test,bench]'
	rm -f $(VENV)/.installed-* && touch $@

install: $(STAMP)

demo: install
	$(BIN)/tiereg demo --out demo-output

test: install
	$(BIN)/python -m pytest -q

bench: install
	$(BIN)/python benchmarks/grid.py
	$(BIN)/python benchmarks/coarse.py

clean:
	rm -rf $(VENV) demo-output .pytest_cache
