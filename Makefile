# Two commands do all the set-up on a fresh machine:
#   make demo   -- create .venv, install, run the demo
#   make test   -- create .venv, install, run lint and the test suite
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test lint bench-sim bench-calibration clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e '.[dev,train]'
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/roadside demo

lint: $(STAMP)
	$(BIN)/ruff check .

test: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/python -m pytest -q

bench-sim: $(STAMP)
	$(BIN)/roadside bench sim

bench-calibration: $(STAMP)
	$(BIN)/roadside bench calibration

clean:
	rm -rf $(VENV) out .pytest_cache .ruff_cache
