.PHONY: demo test install lint goldens bench clean
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

$(STAMP): setup.cfg pyproject.toml
	@test -x $(PY) || python3 -m venv $(VENV)
	$(PY) -m pip install --disable-pip-version-check -q -e '.[dev]'
	@touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/bgs demo

test: $(STAMP)
	$(VENV)/bin/ruff check .
	$(PY) -m pytest

# Write this CPU's tests/golden/<case>.<cpu>.json from fresh runs; commit only with the reason.
goldens: $(STAMP)
	BGS_UPDATE_GOLDENS=1 $(PY) -m pytest -q tests/test_golden.py

lint: $(STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .

clean:
	rm -rf $(VENV) demo build *.egg-info .pytest_cache .ruff_cache
