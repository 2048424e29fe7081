# Two commands do all the set-up on a fresh machine:
#   make demo   -- create .venv, install, run the demo
#   make test   -- create .venv, install, run lint and the test suite
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test lint bench-sim bench-calibration example-site clean

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

# The example site's recording and masks (made here, not shipped; deploy/sites/example/site.yaml names them), which
# `docker compose up` on the example site needs.
EXAMPLE := deploy/sites/example
EXAMPLE_ORIGIN := 42.22939632,-83.73899854,265.0
example-site: $(STAMP)
	$(BIN)/roadside sim --site state_ellsworth --cameras NE,T_SW --seconds 60 --out $(EXAMPLE)/recording
	$(BIN)/roadside calibrate --landmarks $(EXAMPLE)/recording/landmarks/NE.json --kind fisheye \
	    --origin $(EXAMPLE_ORIGIN) --out $(EXAMPLE)/masks/NE.npz
	$(BIN)/roadside calibrate --landmarks $(EXAMPLE)/recording/landmarks/T_SW.json --kind pinhole \
	    --origin $(EXAMPLE_ORIGIN) --out $(EXAMPLE)/masks/T_SW.npz

clean:
	rm -rf $(VENV) out .pytest_cache .ruff_cache
