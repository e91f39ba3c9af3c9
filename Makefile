.PHONY: demo test install system-deps lint goldens bench clean
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

# the shared libraries pip cannot install (Open3D's libusb, OpenMP): checked on every run, since
# a machine can lose them while keeping .venv; as root they are installed, else the command named
system-deps:
	@bash scripts/system-deps.sh

# the numba kernels are compiled here, once, for this CPU (bgs_batch/warmup.py): a user's first
# `bgs run` then tracks its first frame in seconds instead of after half a minute of JIT
$(STAMP): setup.cfg pyproject.toml
	@test -x $(PY) || python3 -m venv $(VENV)
	$(PY) -m pip install --disable-pip-version-check -q -e '.[dev]'
	$(PY) -m bgs_batch.warmup
	@touch $(STAMP)

install: system-deps $(STAMP)

demo: install
	$(VENV)/bin/bgs demo

test: install
	$(VENV)/bin/ruff check .
	$(PY) -m pytest

# Write tests/golden/<case>.json from fresh runs pinned to x86-64-v3; commit only with the reason.
goldens: install
	BGS_UPDATE_GOLDENS=1 $(PY) -m pytest -q tests/test_golden.py

lint: $(STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .

clean:
	rm -rf $(VENV) demo build *.egg-info .pytest_cache .ruff_cache
