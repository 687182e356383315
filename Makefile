# The README's two commands: `make demo` and `make test`. Each does all set-up
# on a fresh machine: system packages for Open3D, a virtual environment, install.
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.tumor3d-installed
DEMO_OUT ?= demo-out

.PHONY: demo test setup system-deps lint bench evaluate-real clean

demo: setup
	$(BIN)/tumor3d demo --out $(DEMO_OUT)

test: setup
	$(BIN)/python -m pytest -q

setup: system-deps $(STAMP)

system-deps:
	@sh scripts/system-deps.sh

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e ".[test]"
	@touch $(STAMP)

lint: setup
	$(BIN)/ruff check .

bench: setup
	$(BIN)/python benchmarks/bench_flow.py

clean:
	rm -rf $(VENV) $(DEMO_OUT) .pytest_cache .ruff_cache
