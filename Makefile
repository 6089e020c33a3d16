# tiereg — set-up, demo, tests and benchmarks. Everything installs into .venv.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed-$(shell cat pyproject.toml | cksum | cut -d' ' -f1)

.PHONY: install browser demo test test-fast bench bench-peers bench-quick clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip

$(STAMP): $(BIN)/python pyproject.toml
	$(BIN)/python -m pip install --quiet -e '.[report,simulate,test,bench,distributed,calibrate]'
	rm -f $(VENV)/.installed-* && touch $@

install: $(STAMP)

demo: install
	$(BIN)/tiereg demo --out demo-output

test: install browser
	$(BIN)/python -m pytest -q -n auto

# the fast tier: the suite without the slow end-to-end registrations (pytest marker `slow`),
# about a minute on 2 cores; `make test` runs both tiers
test-fast: install
	$(BIN)/python -m pytest -q -n auto -m "not slow"

# The report's test opens report.html in headless Chromium (Debian package chromium).
browser:
	@command -v chromium >/dev/null || command -v chromium-browser >/dev/null || \
	  { $(SUDO) apt-get update -qq && $(SUDO) apt-get install -y -qq --no-install-recommends \
	    chromium >/dev/null; } || \
	  echo "Chromium could not be installed: the report's browser test is skipped (fails in CI)"

bench: install bench-peers
	$(BIN)/python benchmarks/grid.py
	$(BIN)/python benchmarks/coarse.py
	$(BIN)/python benchmarks/coarse.py --timing
	$(BIN)/python benchmarks/fine.py
	$(BIN)/python benchmarks/precision.py
	$(BIN)/python benchmarks/control.py
	$(BIN)/python benchmarks/orientation.py
	$(BIN)/python benchmarks/calibration.py
	$(BIN)/python benchmarks/no_overlap_power.py
	$(BIN)/python benchmarks/no_overlap_power.py --overlap 0.6 0.7
	$(BIN)/python benchmarks/verdict.py --jobs 2
	$(BIN)/python benchmarks/fine_far.py
	cd benchmarks && ../$(BIN)/python scale.py && ../$(BIN)/python scale_report.py
	$(BIN)/python benchmarks/sfm.py

bench-quick: install
	$(BIN)/python benchmarks/coarse.py --quick
	$(BIN)/python benchmarks/fine.py --quick
	$(BIN)/python benchmarks/verdict.py --quick
	$(BIN)/python benchmarks/fine_far.py --quick

# Peers run side by side in the benchmarks: CloudCompare (Debian package), Open3D (needs the
# Debian package libusb-1.0-0), small_gicp and xdem. Best effort: a peer that cannot be installed
# is left out of the tables, and the benchmark says so.
SUDO := $(shell [ "$$(id -u)" = 0 ] || echo sudo)
bench-peers: install
	@command -v CloudCompare >/dev/null || command -v cloudcompare >/dev/null || \
	  { $(SUDO) apt-get update -qq && $(SUDO) apt-get install -y -qq --no-install-recommends \
	    cloudcompare libusb-1.0-0 >/dev/null; } || \
	  echo "CloudCompare could not be installed: the benchmarks leave it out"
	@$(BIN)/python -c "import open3d" 2>/dev/null || \
	  $(BIN)/python -m pip install --quiet -e '.[bench-open3d]' || \
	  echo "Open3D could not be installed: the benchmarks leave it out"
	@$(BIN)/python -c "import small_gicp, xdem" 2>/dev/null || \
	  $(BIN)/python -m pip install --quiet -e '.[bench-peers]' || \
	  echo "small_gicp or xdem could not be installed: the benchmarks leave them out"

clean:
	rm -rf $(VENV) demo-output .pytest_cache
