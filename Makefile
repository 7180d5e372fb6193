# Two entry points for a fresh machine: `make eval` (set up, then the main job) and
# `make test` (set up, then the test suite). Both install what the project needs.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
export MUJOCO_GL ?= egl
export PYOPENGL_PLATFORM ?= egl

.PHONY: setup eval test test-fast lint bench guard guard-quick docs results gallery
setup: $(VENV)/.installed

$(VENV)/.installed: pyproject.toml scripts/setup-system.sh
	bash scripts/setup-system.sh
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e '.[all,test,docs]'
	touch $@

eval: setup
	$(BIN)/flowerpose eval

# A worker a core and one more (at most 4): many tests wait (a virtual board's clock, a
# browser, Ray starting up), and the extra worker works meanwhile. A test file's tests run
# on one worker, so its module fixtures are made once.
WORKERS := $(shell python3 -c "import os; print(min(4, (os.cpu_count() or 1) + 1))")
test: setup
	$(BIN)/python -m pytest -q -n $(WORKERS) --dist loadfile

# The tests of under a second each, while working (the full suite is `make test`).
test-fast: setup
	$(BIN)/python -m pytest -q -m "not slow"

# The guard: the working tree against the base its accepted decisions name, both on the
# same fresh plants (flowerpose guard). guard-quick is CI's (the oracle, field and hard
# presets and the real plant as it is and thinned); guard is the whole battery, the full
# loop and pollination included, with the trend on the fixed seeds: run it before a change
# to pipeline/ or sim/ is called done. The real plant is the developers' copy beside the
# checkout (FLOWERPOSE_SHARED), else `flowerpose data fetch paper-plant-3`'s.
SHARED ?= $(or $(FLOWERPOSE_SHARED),../shared)
REAL ?= $(firstword $(wildcard $(SHARED)/real/paper-plant-3) runs/paper-plant-3)
guard-quick: setup $(REAL)
	$(BIN)/flowerpose guard --quick --real $(REAL) --out runs/guard-quick --overwrite

guard: setup $(REAL)
	$(BIN)/flowerpose guard --trend --real $(REAL) --out runs/guard --overwrite

runs/paper-plant-3: | setup
	$(BIN)/flowerpose data fetch paper-plant-3 --to $@

lint: setup
	$(BIN)/ruff check .

bench: setup
	$(BIN)/flowerpose bench

# The results page from fresh runs of the current commit (a clean tree), then the gallery.
results: setup
	bash scripts/results.sh

# The gallery's pictures and the sample outputs (docs/gallery.md, docs/what-you-get.md).
gallery: setup
	bash scripts/gallery.sh

docs: setup
	$(BIN)/python scripts/cli_reference.py
	$(BIN)/mkdocs build --strict
