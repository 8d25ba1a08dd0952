# BagIt: `make demo` runs the main job, `make test` the linter, the type checker and the whole test suite (what CI runs),
# `make test-fast` the tests that need no other process, no browser and no minutes (docs/testing.md).
# Both create .venv in the repository root and install what is needed, system packages included.
# Python packages come from requirements.lock (every version pinned: the ones that made the records in
# bench/results/); pyproject.toml keeps the ranges BagIt works with. `make lock` updates the lock after a
# change to pyproject.toml (keeping every pin it can), `make lock UPGRADE=1` moves every pin to the newest release.

PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV := .venv
BIN := $(VENV)/bin
LOCK := requirements.lock
# The machines the lock is for: the records' Python, on Linux x86_64 with glibc 2.35 or newer (open3d 0.20 needs it).
LOCK_TARGET := --python-version 3.11 --python-platform x86_64-manylinux_2_35
APT_PACKAGES := libusb-1.0-0 libosmesa6 libgl1 libglib2.0-0 libgomp1 chromium chromium-driver
export MUJOCO_GL ?= osmesa
export PYOPENGL_PLATFORM ?= osmesa

.PHONY: demo test test-fast lint sysdeps setup lock bench clean

sysdeps:
	@missing=""; for p in $(APT_PACKAGES); do dpkg -s $$p >/dev/null 2>&1 || missing="$$missing $$p"; done; \
	if [ -n "$$missing" ]; then \
	  if [ "$$(id -u)" = "0" ]; then \
	    echo "installing system packages:$$missing"; \
	    DEBIAN_FRONTEND=noninteractive apt-get update -q && DEBIAN_FRONTEND=noninteractive apt-get install -y -q --no-install-recommends$$missing; \
	  else \
	    echo "missing system packages; run:  sudo apt-get install -y$$missing"; exit 1; \
	  fi; \
	fi

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip

# The lock's exact versions, then BagIt itself without resolving anything; `pip check` fails when the lock
# no longer covers pyproject.toml (run `make lock`). A changed lock or pyproject.toml installs again.
$(VENV)/.installed: $(LOCK) pyproject.toml | $(BIN)/python
	$(BIN)/pip install -q -r $(LOCK)
	$(BIN)/pip install -q --no-deps -e .
	$(BIN)/pip check
	touch $@

# uv's resolver, at the version the lock itself pins, writes the lock from pyproject.toml's dependencies and extras.
lock: | $(BIN)/python
	$(BIN)/pip install -q "$$(grep -sE '^uv==' $(LOCK) || echo uv)"
	$(BIN)/uv pip compile pyproject.toml --extra dev --extra cluster --extra learn $(LOCK_TARGET) --custom-compile-command "make lock" \
	  $(if $(UPGRADE),--upgrade) --quiet -o $(LOCK)

# BagIt's own bytecode, compiled once here: an editable checkout has none, and where Python may not write it
# (PYTHONDONTWRITEBYTECODE) every process of a run or of the suite would compile its imports again (~0.2 s each).
setup: sysdeps $(VENV)/.installed
	$(BIN)/python -c 'from bagit.bench.common import compile_bagit; compile_bagit()'

demo: setup
	$(BIN)/bagit up exp02 --exit-when-done

# Two pytest-xdist workers by default (what CI runs): a file whole on one, and the files that start processes or
# time a bus one after another as one unit of work (tests/conftest.py), so those never share the cores with each
# other. TEST_WORKERS=0 runs it serially (about 1.6x the wall time on 2 cores).
TEST_WORKERS ?= 2
test: setup lint
	$(BIN)/python -m pytest -q $(if $(filter-out 0,$(TEST_WORKERS)),-n $(TEST_WORKERS) --dist loadfile)

# The markers are registered in pyproject.toml's [tool.pytest.ini_options]; a folder runs alone too: pytest tests/planner
FAST_MARKERS := not slow and not processes and not browser
test-fast: setup
	$(BIN)/python -m pytest -q -m "$(FAST_MARKERS)"

# Lint (ruff) and type check (mypy, through tools/typecheck.py): both configured in pyproject.toml.
lint: setup
	$(BIN)/ruff check .
	$(BIN)/python tools/typecheck.py

bench: setup
	$(BIN)/bagit bench stages

clean:
	rm -rf $(VENV) build dist *.egg-info .pytest_cache
